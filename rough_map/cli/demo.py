"""``rough-map demo``: the whole story on embedded default data."""

from __future__ import annotations

import argparse
import math

import numpy as np

from rough_map.cli._common import table


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="run rough_map on built-in synthetic terrain and print what it finds",
        description="Generate seeded synthetic terrain of every ISO 8608 class and every "
        "named surface, estimate R and w, and print them next to the truth.",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--patches", type=int, default=10, help="patches per surface (default 10)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rough_map import iso8608, terrain
    from rough_map.patch import DEFAULT_SPACING as B
    from rough_map.psd import patch_roughness

    n = 112
    rng = np.random.default_rng(args.seed)
    rows = []

    def estimate(make):
        stack = np.stack([make(rng) for _ in range(args.patches)])
        est = patch_roughness(stack, B)
        return (
            math.exp(np.mean([math.log(e.R) for e in est])),
            float(np.mean([e.w for e in est])),
            float(np.mean([e.rms for e in est])),
        )

    print(
        "rough_map demo: PSD roughness of synthetic terrain "
        f"({args.patches} patches of {n * B:.3f} m at {B * 1e3:g} mm each, seed {args.seed})"
    )
    print()
    for cls in iso8608.CLASSES:
        R, w, rms = estimate(
            lambda g, c=cls: iso8608.synthesize_surface((4 * n, 4 * n), B, c, -2.0, seed=g)[:n, :n]
        )
        rows.append(
            [
                f"ISO {cls}",
                f"{iso8608.PHI0[cls]:.2e}",
                "-2.00",
                f"{R:.2e}",
                f"{w:.2f}",
                f"{rms * 1e3:.2f}",
                str(iso8608.iso_class(R)),
            ]
        )
    for name, spec in terrain.SURFACES.items():
        R, w, rms = estimate(lambda g, nm=name: terrain.generate(nm, (n, 4 * n), B, seed=g)[:, :n])
        rows.append(
            [
                name,
                f"{spec.R:.2e}",
                f"{spec.w:.2f}",
                f"{R:.2e}",
                f"{w:.2f}",
                f"{rms * 1e3:.2f}",
                str(iso8608.iso_class(R)),
            ]
        )
    print(table(rows, ["surface", "true R", "true w", "R m^3/rad", "w", "rms mm", "ISO"]))
    return 0
