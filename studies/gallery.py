"""Gallery: images of every built-in scenario, rendered by the env itself (``render_mode="rgb_array"``).

    python -m studies.gallery --out docs/figures            # the documentation's images, ~1 min
    python -m studies.gallery --quick --out /tmp/gallery    # tiny frames, short horizons (tests)

Writes, for each built-in scenario (``ee_formation_env.BUILTIN_SCENARIOS``), ``scenario_<name>.png``: the
scenario at its start (left) and formed by the ``adaptive_jacobian`` reference (right), side by side, from
reset seed 0 with one camera for the whole episode. Then two short animations, ``episode_planar_square.gif``
and ``episode_spatial_tetrahedron.gif``: one episode of each under the same reference, one frame every few
control steps. The formation's edges are red; the target shape, placed where it best fits the end-effectors,
is the light-blue ghost (see ``docs/spaces.md``, Rendering). Needs imageio (the ``video`` extra).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import ee_formation_env
from ee_formation_env.baselines import make_policies
from ee_formation_env.baselines.reference.team import PolicyTeam

POLICY = "adaptive_jacobian"
FORMED_SECONDS = {"planar": 4.0, "spatial": 10.0}  # simulated time after which the image is "formed"
ANIMATED = ("planar_square", "spatial_tetrahedron")
ANIMATION_SECONDS = {"planar": 3.0, "spatial": 8.0}  # simulated time shown by an animation
ANIMATION_FRAMES = 60  # frames per animation (about; one every few control steps)
GAP = 8  # pixels of white between the two panels of a scenario image


def _family(name: str) -> str:
    return "planar" if name.startswith("planar") else "spatial"


def _rollout(name: str, seconds: float, width: int, height: int, frames: int) -> list[np.ndarray]:
    """Frames of one ``POLICY`` episode from reset seed 0: the first at the start, the last after ``seconds``
    simulated (or at the episode's end), ``frames`` in all, evenly spaced in control steps."""
    env = ee_formation_env.parallel_env(name, render_mode="rgb_array", render_width=width, render_height=height)
    try:
        team = PolicyTeam(make_policies(POLICY, env))
        observations, _ = env.reset(seed=0)
        team.reset()
        steps = max(1, int(round(seconds / env.scenario.control_dt)))
        every = max(1, steps // max(1, frames - 1))
        images = [env.render()]
        for step in range(1, steps + 1):
            observations, _, _, _, _ = env.step(team(observations))
            if not env.agents:
                images.append(env.render())
                break
            if step % every == 0 or step == steps:
                images.append(env.render())
        return images
    finally:
        env.close()


def scenario_image(name: str, width: int, height: int, seconds: float) -> np.ndarray:
    """The scenario at its start and formed, side by side (one RGB uint8 array)."""
    start, *_, formed = _rollout(name, seconds, width, height, frames=2)
    gap = np.full((height, GAP, 3), 255, dtype=np.uint8)
    return np.concatenate([start, gap, formed], axis=1)


def main(argv: list[str] | None = None) -> list[Path]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("docs/figures"), help="output folder")
    parser.add_argument("--width", type=int, default=480, help="pixels per panel (default 480)")
    parser.add_argument("--height", type=int, default=360, help="pixels per panel (default 360)")
    parser.add_argument("--gif-width", type=int, default=360, help="pixels of an animation frame (default 360)")
    parser.add_argument("--gif-height", type=int, default=270, help="pixels of an animation frame (default 270)")
    parser.add_argument("--quick", action="store_true", help="tiny frames and short horizons (tests)")
    parser.add_argument("--only", action="append", choices=sorted(ee_formation_env.BUILTIN_SCENARIOS),
                        help="render only these scenarios (repeatable); animations of the others are skipped")
    args = parser.parse_args(argv)
    try:
        import imageio.v3 as iio
    except ImportError:
        parser.exit(2, "studies.gallery needs imageio: pip install -e \".[video]\"\n")
    if args.quick:
        args.width, args.height, args.gif_width, args.gif_height = 64, 48, 48, 36
    scale = 0.05 if args.quick else 1.0
    names = args.only or list(ee_formation_env.BUILTIN_SCENARIOS)
    args.out.mkdir(parents=True, exist_ok=True)
    written = []
    for name in names:
        path = args.out / f"scenario_{name}.png"
        iio.imwrite(path, scenario_image(name, args.width, args.height, FORMED_SECONDS[_family(name)] * scale))
        written.append(path)
        print(f"wrote {path}")
    for name in ANIMATED:
        if name not in names:
            continue
        seconds = ANIMATION_SECONDS[_family(name)] * scale
        frames = _rollout(name, seconds, args.gif_width, args.gif_height, 6 if args.quick else ANIMATION_FRAMES)
        frames += [frames[-1]] * (len(frames) // 4)  # hold the formed shape a moment before looping
        path = args.out / f"episode_{name}.gif"
        iio.imwrite(path, np.stack(frames), duration=80, loop=0)  # 80 ms per frame
        written.append(path)
        print(f"wrote {path} ({len(frames)} frames, {path.stat().st_size / 1e3:.0f} kB)")
    return written


if __name__ == "__main__":
    main()
