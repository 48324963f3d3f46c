// dtraced::scene JSON values: the pieces of the scene format that more than one reader or writer
// needs, so that a scene file, the canonical form and a wire message agree on them.
//
// Owns: how a vector, a colour and a number that must fit a float are read (jsonio's rules plus
// the scene's: every number within the float range, colours non-negative); the keys, limits and
// canonical writing of a render block, which is also the settings object of a lease and of a
// stored job (protocol/messages.h). The limits are description.h's.
//
// Stateless functions: thread-safe (a jsonio::Reader passed in belongs to its caller).
#pragma once

#include <array>
#include <optional>
#include <string_view>

#include <boost/json/object.hpp>
#include <boost/json/storage_ptr.hpp>
#include <boost/json/value.hpp>

#include "jsonio/reader.h"
#include "scene/description.h"

namespace dtraced::scene {

// Any JSON number with |x| <= FLT_MAX ("number x is outside the float range ..."); -0 is +0.
std::optional<double> read_float(jsonio::Reader& r, const boost::json::value& v, const jsonio::Path& at);
// [x, y, z], each a read_float.
std::optional<Vec3d> read_vec3(jsonio::Reader& r, const boost::json::value& v, const jsonio::Path& at);
// A read_vec3 whose channels are >= 0.
std::optional<Color> read_color(jsonio::Reader& r, const boost::json::value& v, const jsonio::Path& at);

// The keys of a render block, in canonical order.
inline constexpr std::array<std::string_view, 14> kRenderKeys = {
    "width",        "height",      "samples", "max_depth", "background", "seed", "frame",
    "error_target", "min_samples", "fps",     "frames",    "exposure",   "tone", "branch_cutoff"};

// Reads the keys of kRenderKeys that `f` holds into `s` (keys are checked by the caller), with the
// limits of description.h: width, height, samples, max_depth, background, seed and frame as
// `need` says; error_target, min_samples, fps, frames, exposure, tone and branch_cutoff always
// optional, so that settings stored before adaptive sampling, animation, tone curves and the
// cut-off existed still read.
// "frames" is {"first": F, "last": L, "step": S} (step optional, 1), first <= last, at most
// kMaxFrames frames; "tone" one of image::kToneCurveNames; "exposure" in stops. `Settings` is RenderSettings, or
// Overrides (overrides.h), whose fields are set only for the keys present.
template <typename Settings>
void read_render_settings(jsonio::Fields& f, Settings& s, jsonio::Need need);

// The canonical render block: every key of kRenderKeys but error_target and min_samples, which
// are written only when adaptive sampling is on, and fps, frames, exposure, tone and
// branch_cutoff, written only when they differ from their defaults (so that scenes and stored jobs
// without them keep the text, and the digests, they always had).
boost::json::object render_settings_object(const RenderSettings& s, const boost::json::storage_ptr& sp = {});
// {"first", "last", "step"}: how a render block (and a job submission) writes a frame range.
boost::json::value frame_range_value(const FrameRange& range, const boost::json::storage_ptr& sp = {});
// [x, y, z] with jsonio::exact_number.
boost::json::value vec3_value(const Vec3d& v, const boost::json::storage_ptr& sp = {});

}  // namespace dtraced::scene
