// dtraced::scene OBJ meshes: the text of a Wavefront OBJ file into the transformed float triangles
// of a scene::Mesh (description.h). The second half of loading a "mesh" object; load.cpp reads the
// JSON and the file, this reads the OBJ.
//
// Owns: the rules an OBJ must meet to be part of a scene (every vertex coordinate a finite number,
// every face index in range, a bounded triangle count, finite coordinates after the transform)
// and the transform's arithmetic, which fixes the triangles' bits: every host that loads the same
// OBJ text with the same transform gets the same floats, and so the same pixels.
//
// Parsing is tinyobjloader's (faces triangulated by it). Two things it does silently that a scene
// must not: it reads a coordinate it cannot parse ("nan", "1.0.0", "abc") as 0, and it skips
// polygons with an out-of-range index. The first is caught by checking the tokens of each "v"
// line before parsing (a check, not a second parser: the numbers still come from tinyobjloader),
// the second by refusing its out-of-range warning and checking every index again after it.
//
// Stateless functions: thread-safe.
#pragma once

#include <cstddef>

#include "scene/description.h"
#include "util/result.h"

namespace dtraced::scene {

// Fills mesh.vertices and mesh.degenerate_triangles from mesh.obj under mesh's transform. On
// failure returns one or more errors (each message "line N: problem" when the problem has a line;
// path and file empty, for the caller to fill in with the field and prefix with the OBJ file),
// and leaves the vertices empty. `max_triangles` bounds the triangles this mesh may add (what is
// left of the scene's budget); more is an error.
util::Result<void, util::Errors> build_obj_mesh(Mesh& mesh, std::size_t max_triangles);

// Whether a triangle of these float vertices has zero area: cross(v1 - v0, v2 - v0) computed in
// double from the float coordinates is zero (or not finite). The same test accel uses to decide
// that a triangle can never be hit (accel::detail::shape_is_valid).
bool triangle_is_degenerate(const math::Vec3f& v0, const math::Vec3f& v1, const math::Vec3f& v2);

}  // namespace dtraced::scene
