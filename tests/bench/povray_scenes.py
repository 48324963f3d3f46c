#!/usr/bin/env python3
"""Writes one scene twice, as a dtraced scene (JSON) and as a POV-Ray 3.7 scene, for
tests/bench/povray_compare.sh.

Usage: povray_scenes.py NAME OUTDIR [WIDTH HEIGHT]
  NAME  whitted10   ten spheres on a plane (diffuse, mirror, glass that also reflects), two
                    point lights: a Whitted scene of the kind dtraced started from
        spheres10k  10,000 spheres on a jittered grid (mostly diffuse, some mirror and glass)
Writes OUTDIR/NAME.json and OUTDIR/NAME.pov. Both hold the same camera, objects and lights and the
same branch cut-off (BAILOUT); the shading models are matched as far as POV-Ray's allow (see the
notes in `pov_finish`). Also OUTDIR/NAME-ref.json: the dtraced scene with dtraced's default
cut-off (1e-6), for its converged reference, so that what the cut-off loses counts as error. The
scenes are a pure function of NAME (a fixed random seed), so every run compares the same pictures.
"""

import json
import math
import random
import sys

MAX_DEPTH = 5
# POV-Ray's point lights fall off as 2 / (1 + (d / FADE)^2) with fade_power 2: with a small
# FADE that is 2 FADE^2 / d^2 beyond a few FADE, so a light colour of I / (2 pi FADE^2) gives
# dtraced's I / (pi d^2) (dtraced's Lambert term carries the 1 / pi; POV's diffuse does not).
FADE = 0.01
# A branch (reflected, refracted or seen through) whose weight on the pixel is below this is not
# traced: POV-Ray's default adc_bailout, written to both scenes (dtraced's render.branch_cutoff).
BAILOUT = 1.0 / 255.0


def material(color, diffuse=1.0, specular=0.0, shininess=32.0, reflectivity=0.0, transparency=0.0, ior=1.5):
    return {"color": list(color), "diffuse": diffuse, "specular": specular, "shininess": shininess,
            "reflectivity": reflectivity, "transparency": transparency, "ior": ior}


def whitted10():
    glass = dict(diffuse=0.0, specular=0.9, shininess=512, reflectivity=0.06, transparency=0.9, ior=1.5)
    mirror = dict(diffuse=0.1, specular=0.9, shininess=512, reflectivity=0.85)
    plastic = dict(diffuse=1.0, specular=0.5, shininess=64)
    spheres = [
        ((-2.6, 1.0, -1.0), 1.0, (0.95, 0.95, 0.95), mirror),
        ((0.0, 0.9, 0.4), 0.9, (1, 1, 1), glass),
        ((2.5, 0.8, -1.4), 0.8, (0.9, 0.75, 0.4), mirror),
        ((-0.9, 0.35, 2.1), 0.35, (0.85, 0.15, 0.1), plastic),
        ((1.3, 0.45, 2.0), 0.45, (1, 1, 1), glass),
        ((-3.2, 0.4, 1.8), 0.4, (0.1, 0.6, 0.2), plastic),
        ((3.4, 0.5, 1.2), 0.5, (0.15, 0.3, 0.85), plastic),
        ((0.9, 0.6, -3.0), 0.6, (0.9, 0.5, 0.1), plastic),
        ((-1.2, 0.3, -2.6), 0.3, (0.6, 0.2, 0.7), plastic),
        ((2.0, 0.25, 0.6), 0.25, (0.95, 0.9, 0.2), plastic),
    ]
    objects = [{"type": "plane", "loc": [0, 0, 0], "normal": [0, 1, 0],
                "material": material((0.6, 0.6, 0.58), diffuse=1.0, specular=0.1, shininess=16,
                                     reflectivity=0.1)}]
    for loc, radius, color, kind in spheres:
        objects.append({"type": "sphere", "loc": list(loc), "radius": radius, "material": material(color, **kind)})
    return {
        "camera": {"position": [0, 2.4, 8.0], "look_at": [0, 0.7, 0], "up": [0, 1, 0], "fov": 42},
        "render": {"width": 1280, "height": 720, "samples": 1, "max_depth": MAX_DEPTH,
                   "background": [0.08, 0.09, 0.12], "seed": 7},
        "scene_objects": objects,
        "scene_lights": [
            {"type": "point", "loc": [-4, 6, 5], "color": [1, 0.95, 0.88], "intensity": 320},
            {"type": "point", "loc": [5, 4, 2], "color": [0.8, 0.88, 1], "intensity": 120},
        ],
    }


def spheres10k():
    rng = random.Random(10000)
    side = 100  # 100 x 100 cells on the ground, one sphere each
    cell = 0.5
    objects = [{"type": "plane", "loc": [0, 0, 0], "normal": [0, 1, 0],
                "material": material((0.5, 0.5, 0.5), diffuse=1.0)}]
    for i in range(side):
        for j in range(side):
            radius = round(rng.uniform(0.08, 0.2), 4)
            x = round((i - side / 2 + 0.5) * cell + rng.uniform(-0.1, 0.1), 4)
            z = round((j - side / 2 + 0.5) * cell + rng.uniform(-0.1, 0.1), 4)
            y = round(radius + rng.uniform(0.0, 0.3), 4)
            color = tuple(round(rng.uniform(0.15, 0.95), 3) for _ in range(3))
            kind = rng.random()
            if kind < 0.1:
                m = material(color, diffuse=0.1, specular=0.8, shininess=256, reflectivity=0.8)
            elif kind < 0.15:
                m = material((1, 1, 1), diffuse=0.0, specular=0.9, shininess=512, reflectivity=0.06,
                             transparency=0.9, ior=1.5)
            else:
                m = material(color, diffuse=1.0, specular=0.3, shininess=32)
            objects.append({"type": "sphere", "loc": [x, y, z], "radius": radius, "material": m})
    return {
        "camera": {"position": [0, 9, 26], "look_at": [0, 0, 2], "up": [0, 1, 0], "fov": 50},
        "render": {"width": 1280, "height": 720, "samples": 1, "max_depth": MAX_DEPTH,
                   "background": [0.1, 0.12, 0.16], "seed": 11},
        "scene_objects": objects,
        "scene_lights": [
            {"type": "point", "loc": [-15, 25, 20], "color": [1, 0.96, 0.9], "intensity": 4000},
            {"type": "point", "loc": [20, 12, 5], "color": [0.8, 0.88, 1], "intensity": 1200},
        ],
    }


SCENES = {"whitted10": whitted10, "spheres10k": spheres10k}


def vec(v):
    # dtraced is right-handed with the camera looking down -z; POV-Ray is left-handed. Mirroring
    # z maps one onto the other, so the picture is the same.
    return "<{:.9g}, {:.9g}, {:.9g}>".format(v[0], v[1], -v[2])


def rgb(v):
    return "rgb <{:.9g}, {:.9g}, {:.9g}>".format(*v)


def pov_finish(m):
    """POV-Ray's nearest equivalent of a dtraced material. What differs:
    - dtraced's highlight is normalised Blinn-Phong times cos(theta); POV's `specular` is
      Blinn-Phong without the cosine, scaled here by dtraced's (n + 8) / 8 normalisation;
    - dtraced weighs the local term by 1 - reflectivity - transparency; POV's transmit lowers the
      diffuse term by the transparency, and `diffuse` is scaled here by 1 - reflectivity;
    - dtraced's transparent part splits by the exact Fresnel term; POV's `fresnel on` reflection
      with `conserve_energy` does the same for the reflected part;
    - a mirror reflection is tinted by the colour in both (`metallic`)."""
    r, t = m["reflectivity"], m["transparency"]
    local = 1.0 - r - t
    s = max(m["shininess"], 1.0)
    parts = ["ambient 0", "diffuse {:.9g}".format(m["diffuse"] * (1.0 - r))]
    spec = m["specular"] * local * (s + 8.0) / 8.0
    if spec > 0:
        parts.append("specular {:.9g} roughness {:.9g}".format(spec, max(1.0 / s, 0.0005)))
    if t > 0:
        parts.append("reflection {{ {:.9g}, {:.9g} fresnel on metallic }} conserve_energy".format(r, r + t))
    elif r > 0:
        parts.append("reflection {{ {:.9g} metallic }}".format(r))
    return "finish { " + " ".join(parts) + " }"


def pov_object(o):
    m = o["material"]
    pigment = "pigment {{ rgbt <{:.9g}, {:.9g}, {:.9g}, {:.9g}> }}".format(*m["color"], m["transparency"])
    interior = " interior {{ ior {:.9g} }}".format(m["ior"]) if m["transparency"] > 0 else ""
    body = " " + pigment + " " + pov_finish(m) + interior
    if o["type"] == "sphere":
        return "sphere {{ {}, {:.9g}{} }}".format(vec(o["loc"]), o["radius"], body)
    if o["type"] == "plane":
        n = o["normal"]
        d = sum(a * b for a, b in zip(n, o["loc"]))
        return "plane {{ {}, {:.9g}{} }}".format(vec(n), d, body)
    raise ValueError("povray_scenes.py: no POV-Ray form for object type " + o["type"])


def to_pov(scene):
    cam, render = scene["camera"], scene["render"]
    w, h = render["width"], render["height"]
    hfov = math.degrees(2 * math.atan(math.tan(math.radians(cam["fov"]) / 2) * w / h))
    out = [
        "// Written by tests/bench/povray_scenes.py: the same scene as the .json beside it.",
        "#version 3.7;",
        "global_settings {{ assumed_gamma 1.0 max_trace_level {} adc_bailout {:.17g} }}".format(
            render["max_depth"] + 1, render.get("branch_cutoff", 1e-6)),
        "background {{ {} }}".format(rgb(render["background"])),
        "camera {{ perspective location {} look_at {} sky {} right x*{:.9g} up y angle {:.9g} }}".format(
            vec(cam["position"]), vec(cam["look_at"]), vec(cam["up"]), w / h, hfov),
    ]
    for light in scene["scene_lights"]:
        scale = light["intensity"] / (2 * math.pi * FADE * FADE)
        out.append("light_source {{ {} {} fade_distance {:.9g} fade_power 2 }}".format(
            vec(light["loc"]), rgb([c * scale for c in light["color"]]), FADE))
    out.extend(pov_object(o) for o in scene["scene_objects"])
    return "\n".join(out) + "\n"


def main(argv):
    if len(argv) not in (3, 5) or argv[1] not in SCENES:
        sys.exit("usage: povray_scenes.py {" + "|".join(SCENES) + "} OUTDIR [WIDTH HEIGHT]")
    name, outdir = argv[1], argv[2]
    scene = SCENES[name]()
    if len(argv) == 5:
        scene["render"]["width"], scene["render"]["height"] = int(argv[3]), int(argv[4])
    scene["render"]["branch_cutoff"] = BAILOUT
    with open("{}/{}.json".format(outdir, name), "w") as f:
        json.dump(scene, f, indent=1)
        f.write("\n")
    reference = json.loads(json.dumps(scene))
    del reference["render"]["branch_cutoff"]
    with open("{}/{}-ref.json".format(outdir, name), "w") as f:
        json.dump(reference, f, indent=1)
        f.write("\n")
    with open("{}/{}.pov".format(outdir, name), "w") as f:
        f.write(to_pov(scene))


if __name__ == "__main__":
    main(sys.argv)
