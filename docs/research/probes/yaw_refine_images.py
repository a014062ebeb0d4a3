"""Which image the parallax-free yaw should re-centre: the shipped network's G, U or G - U.

    .venv/bin/python docs/research/probes/yaw_refine_images.py out/ood/worlds/hard-terrace-16b-c30

On a world of the out-of-distribution suite (`benchmarks/run_ood.sh` makes them under
out/ood/worlds), each query of session 01 (as the suite queries them; --tilt adds more) is
compared with its nearest map scan of session 00 within 5 m: the plain phase-correlation
yaw of G, and `yaw_refine.refine_one` on G, on U and on G - U (the BEV summed over
heights). Prints mean, median and largest absolute error against the ground truth, and
how far G - U's winning position lies from the map sensor's true position.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

# Beside the dated notes; ood_suite and _common stay in benchmarks/ (the repository root
# is three folders up), sibling probes import each other from here.
sys.path[:0] = [
    str(Path(__file__).resolve().parent),
    str(Path(__file__).resolve().parents[3] / "benchmarks"),
]
import ood_suite as suite  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    suite.add_world_arguments(ap)
    ap.add_argument("--model", default="default")
    args = ap.parse_args()

    from _common import print_header

    from disco_cli.io.poses import xy_yaw
    from disco_cli.model import load_model
    from disco_cli.model.yaw import estimate_yaw, wrap_deg
    from disco_cli.model.yaw_refine import refine_one

    print_header("yaw_refine_images")
    model = load_model(args.model)
    if not getattr(model, "two_channel", False):
        sys.exit(f"{args.model}: not a residual (two-channel) network; nothing to compare")
    max_range = model.bev_config.max_range
    world = suite.embed_world(model, args.world, args.tilt)
    mf, qf = world.map_features, world.query_features
    mx, my, myaw = xy_yaw(world.map_poses)
    qx, qy, qyaw = xy_yaw(world.queries.poses)
    images = {
        "re-centred G": lambda f: f[0],
        "re-centred U": lambda f: f[1],
        "re-centred G - U": model.refine_image,  # what the shipped search re-centres
    }
    errors: dict[str, list[float]] = {"plain G": [], **{k: [] for k in images}}
    position_errors = []  # of G - U's winning position against the map sensor's true one
    for i in range(len(qf)):
        d = np.hypot(mx - qx[i], my - qy[i])
        j = int(d.argmin())
        if d[j] > suite.RADIUS:
            continue
        true = float(wrap_deg(math.degrees(qyaw[i] - myaw[j])))
        plain = estimate_yaw(qf[i][0], mf[j][0][None])[0]
        errors["plain G"].append(abs(float(wrap_deg(plain - true))))
        for name, image in images.items():
            got, where, _ = refine_one(image(qf[i]), image(mf[j]), max_range)
            errors[name].append(abs(float(wrap_deg(got - true))))
        # The map sensor in the query's frame: what the winning position estimates.
        c, s = math.cos(qyaw[i]), math.sin(qyaw[i])
        dx, dy = mx[j] - qx[i], my[j] - qy[i]
        position_errors.append(
            float(np.hypot(where[0] - (c * dx + s * dy), where[1] - (-s * dx + c * dy)))
        )
    print(f"{args.world.name}: {len(errors['plain G'])} queries with a map scan within 5 m")
    for name, e in errors.items():
        v = np.array(e)
        print(
            f"  {name:18s} yaw error mean {v.mean():.2f}, median {np.median(v):.2f}, "
            f"max {v.max():.1f} deg; {int((v > 90).sum())} over 90"
        )
    p = np.array(position_errors)
    print(f"  G - U's winning position: {np.median(p):.2f} m from the map sensor (median)")


if __name__ == "__main__":
    main()
