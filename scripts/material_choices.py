"""The measurements behind the per-length material's defaults (docs/material.md, "Choices, measured").

For each variant of the material (stretch rigidity EA, geometric stiffness, the bend/torsion
springs, the follow-the-leader damping), float64, every other field the library default:

- **convergence**: the hidden-check study of docs/material_convergence.md on the ``wavy``
  preset (6 strands, seed 0, grown at 1025 particles; 60 frames of a 0.6 rad, 1.5 Hz shake;
  M = 4): RMS error (mm) at 17 material points of N = 16, 32, 64 against N = 256, and N = 256
  against N = 512;
- **sensitivity**: the same shake at N = 128, with every free particle's initial velocity
  perturbed by 1e-9 m/s in a fixed random direction: the largest final distance (m) between the
  perturbed and unperturbed runs (a stable, non-chaotic step keeps it near 1e-9 × the run's time);
- **numerical damping**: a 0.3 m wisp (4 strands, N = 64) at rest, no gravity, no drag, no
  follow-the-leader, set moving by a transverse velocity 0.5 m/s × (arc length / L); the share of
  the conservative energy (``ams_torch.testing.total_energy``) left after 1 s, at M = 1 and M = 4.

    .venv/bin/python scripts/material_choices.py            # → docs/material_choices.json, a table on stdout
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

import ams_torch as at  # noqa: E402
from ams_torch._bench import machine_info  # noqa: E402
from ams_torch.grooms.groom import resample_strands  # noqa: E402
from ams_torch.apps.motion import Shake  # noqa: E402
from ams_torch.testing import total_energy, wisp  # noqa: E402

import convergence_n  # noqa: E402

F64 = torch.float64
PROXY = 3.2768e-11  # N·m⁴: the bend/torsion rigidity of the per-particle default's springs at 8 mm

#: name → (what, Params changes)
VARIANTS = {
    "default": ("the library default: EA = 8e-3 N, geometric stiffness, no bend/torsion springs, ftl_damping 0.8",
                {}),
    "ftl_damping_0.9": ("as default, ftl_damping = 0.9 (Müller's value, the previous default)",
                        {"ftl_damping": 0.9}),
    "ftl_damping_0.7": ("as default, ftl_damping = 0.7", {"ftl_damping": 0.7}),
    "spec_form": ("as default, geometric stiffness off (the SPEC form)", {"geometric_stiffness": False}),
    "springs": ("as default, bend and torsion springs B_b = B_t = 3.2768e-11 N·m⁴ (with the stretch coupling)",
                {"bend_rigidity": PROXY, "torsion_rigidity": PROXY}),
    "springs_spec_form": ("springs, geometric stiffness off",
                          {"bend_rigidity": PROXY, "torsion_rigidity": PROXY, "geometric_stiffness": False}),
    "springs_previous": ("the previous default: springs, geometric stiffness off, ftl_damping 0.9",
                         {"bend_rigidity": PROXY, "torsion_rigidity": PROXY, "geometric_stiffness": False,
                          "ftl_damping": 0.9}),
    "ea_1": ("as default, EA = 1 N", {"stretch_rigidity": 1.0}),
    "ea_20": ("as default, EA = 20 N (a real hair's)", {"stretch_rigidity": 20.0}),
    "ea_20_spec_form": ("EA = 20 N, geometric stiffness off", {"stretch_rigidity": 20.0, "geometric_stiffness": False}),
    "ea_20_springs": ("EA = 20 N with the springs", {"stretch_rigidity": 20.0, "bend_rigidity": PROXY,
                                                     "torsion_rigidity": PROXY}),
}


def convergence(changes: dict) -> dict:
    case = convergence_n.preset_case("wavy")
    r = convergence_n.convergence(case, "per_length", 4, shown=(), time_check=False, stiffness_cap=1e12, **changes)
    return {"rms_error_mm": r["rms_error_mm"], "order": r["order"], "ratio": r["ratio"], "monotone": r["monotone"],
            "reference_check_mm": r["reference_check"]["rms_error_mm"]}


def sensitivity(changes: dict, n: int = 128, eps: float = 1e-9) -> float:
    case = convergence_n.preset_case("wavy")
    rest = resample_strands(case["fine"], n)
    sim = at.Simulator(rest, at.Params(substeps=4, stiffness_cap=1e12, **changes), dtype=F64)
    a = sim.initial_state()
    g = torch.Generator().manual_seed(0)
    kick = eps * torch.nn.functional.normalize(torch.randn(a.v.shape, generator=g, dtype=F64), dim=-1)
    b = dataclasses.replace(a, v=a.v + kick * (~sim.model.pinned)[..., None])
    for pose in case["poses"]:
        a, b = sim.step(a, pose), sim.step(b, pose)
    return float((a.x - b.x).norm(dim=-1).max())


def damping(changes: dict, substeps: int) -> float:
    rest = wisp(4, 64, length=0.3, dtype=F64)
    p = at.Params(substeps=substeps, gravity=(0.0, 0.0, 0.0), drag=0.0, inextensibility=False, stiffness_cap=1e12,
                  **changes)
    sim = at.Simulator(rest, p, dtype=F64)
    s = sim.initial_state()
    arc = torch.nn.functional.pad((rest[:, 1:] - rest[:, :-1]).norm(dim=-1).cumsum(-1), (1, 0))
    v = torch.zeros_like(s.v)
    v[..., 2] = 0.5 * arc / arc[:, -1:]
    s = dataclasses.replace(s, v=v * (~sim.model.pinned)[..., None])
    e0 = float(total_energy(sim, s))
    for _ in range(60):
        s = sim.step(s, None)
    return float(total_energy(sim, s)) / e0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variants", nargs="*", default=list(VARIANTS))
    ap.add_argument("--out", default=str(REPO / "docs" / "material_choices.json"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    rows = []
    print("| variant | errors N = 16 / 32 / 64 vs 256 (mm) | order | ratio 16→64 | 256 vs 512 (mm) | "
          "sensitivity (m) | energy left after 1 s, M = 1 / 4 |")
    print("|---|---|---|---|---|---|---|")
    for name in args.variants:
        what, changes = VARIANTS[name]
        r = {"variant": name, "what": what, "changes": changes, "convergence": convergence(changes),
             "sensitivity_m": sensitivity(changes), "energy_left": {m: damping(changes, m) for m in (1, 4)}}
        rows.append(r)
        c = r["convergence"]
        print(f"| `{name}` | " + " / ".join(f"{e:.3g}" for e in c["rms_error_mm"]) +
              f" | {c['order']:.2f} | {c['ratio']:.2f} | {c['reference_check_mm']:.2g} | {r['sensitivity_m']:.1e} | "
              f"{r['energy_left'][1]:.3f} / {r['energy_left'][4]:.3f} |", flush=True)
    meta = {"command": "python scripts/material_choices.py" + (" --variants " + " ".join(args.variants)
                                                                 if argv and "--variants" in argv else ""),
            "wall_s": time.perf_counter() - t0, "machine": machine_info()}
    Path(args.out).write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"wrote {args.out} in {meta['wall_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
