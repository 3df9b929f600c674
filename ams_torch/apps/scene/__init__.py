"""Scene files: a TOML description of a whole simulation, validated, built and run.

A scene composes a head, a groom, :class:`~ams_torch.Params`, colliders, a head motion, wind,
the optional stages and the run length. Only the stages a scene names are built and run.
Every key is checked; errors name the key (``scene.toml: [params].stretch_stiffness must be
non-negative ...``). Top level::

    name = "wig_in_wind"          # optional, default: file stem
    description = "..."           # optional
    frames = 120                  # frames to simulate (int >= 1)
    dt = 0.0166667                # s, optional (else params.dt)
    substeps = 1                  # optional (else params.substeps)
    scale = 1.0                   # multiplies the groom's strand count (toward the paper's sizes)

    [head]     mesh = "default" | "none" | "sphere" | path (relative to the scene file)
               subdivisions = 4   (default head), radius = 0.1 (sphere head), collide = true
               sdf_resolution = 64 (head collider SDF)
    [groom]    preset = "straight" | file = "path" | kind = "sphere" | "strand" | "wisp"
               strands, particles, seed, length, radius (sphere/strand/wisp), spread (wisp),
               [groom.growth] overrides for the preset (growth parameters)
               compare_ms = false, compare_offset = [x, y, z] (duplicate the groom as plain
               mass-spring strands, κ_I = κ_α = 0, shifted by the offset: AMS vs MS)
    [params]   any field of ams_torch.Params (integrity_model = "nonhookean", ...)
    [stages]   hair_hair = false, collisions = false, nonhookean = false
    [hair_hair] fields of ams_torch.HairHair (resolution = 64, ...)
    [motion]   type = "static" | "shake" | "nod" | "spin" | "roller_coaster" | "keyframes" |
               "recorded" and the motion's arguments (see ams_torch.apps.motion)
    [wind]     fields of ams_torch.stages.wind.Wind (speed, direction, gust, turbulence, ...)
    [[colliders]] type = "sphere" | "capsule" | "plane" | "hollow_sphere", its arguments,
               follow_head = false, and an optional [colliders.motion] (world pose over time)
    [trim]     frame = 60, point = [x, y, z], normal = [nx, ny, nz] (head frame): at that frame
               strands are cut where they cross the plane (the part on the normal's side goes)

Usage::

    scene = load_scene("datasets/scenes/default.toml")
    run = build(scene)                 # Simulator, motion, wind, ...
    result = simulate(run)             # positions (F, S, N, 3), poses, timings
"""
from ams_torch.apps.scene.build import BuiltScene, build, trim_strands
from ams_torch.apps.scene.run import simulate
from ams_torch.apps.scene.schema import SCENE_DIR, SceneError, load_scene, make_params, parse_scene, read_toml

__all__ = ["SceneError", "load_scene", "parse_scene", "build", "simulate", "BuiltScene", "trim_strands", "SCENE_DIR",
           "read_toml", "make_params"]
