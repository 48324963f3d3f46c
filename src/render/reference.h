// dtraced::render closed-form reference images.
//
// Owns: the exact image of the scenes whose light transport has a closed form, which the error
// report (`dtraced bench error`) and the convergence tests measure renders against. A scene
// qualifies when it holds exactly one object, a plane whose material is purely diffuse
// (specular, reflectivity and transparency all 0), and its lights are
//   point   radiance diffuse * colour / pi * I * cos / d^2 (a plane never shadows itself);
//   sphere  irradiance pi * Le * (R / d)^2 * cos, exact while the sphere lies wholly on one side
//           of the plane (then it is above every shading point's horizon or below it);
//   rect    irradiance by Lambert's polygon formula, Le / 2 * sum of the edges' subtended angles
//           times the cosine of their planes' normals with the surface normal, exact while the
//           rect lies wholly on one side of the plane.
// Camera rays that reach a sphere or rect light's emitting side before the plane see Le, rays
// that miss see the background: everything the renderer can show in such a scene.
//
// A pixel is the mean over a G x G grid of film positions at the sub-cell centres (the renderer's
// box filter, integrated by the midpoint rule). Irradiance varies smoothly inside a pixel, so the
// quadrature error of G = 16 is far below the Monte Carlo noise of any practical render; light
// outlines in view are the exception (their coverage is exact only to 1 / G^2) and a scene meant
// as a reference keeps its lights out of view. Everything is computed in double from the scene
// description and the renderer's own camera mapping.
//
// Thread safety: a pure function of its arguments.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "image/image.h"
#include "render/render_scene.h"
#include "scene/description.h"

namespace dtraced::render {

inline constexpr std::uint32_t kReferenceGrid = 16;
inline constexpr std::uint32_t kMaxReferenceGrid = 64;

// The exact image of `desc` at desc.render's size, or nullopt with `why_not` saying which part of
// the scene has no closed form here. `scene` must be RenderScene::build(desc, ...): its camera
// maps film positions to rays exactly as renders do. `grid` in [1, kMaxReferenceGrid].
std::optional<image::ImageRGBf> closed_form_reference(const scene::SceneDesc& desc, const RenderScene& scene,
                                                      std::uint32_t grid, std::string& why_not);

}  // namespace dtraced::render
