"""How easily the ant tips over under different physics settings (MuJoCo C, no learning).

Each variant builds the U-maze ant (envs.ant_maze.ant_mjcf) with some AntConfig settings and
drives it from the task start with open-loop actions for 1,000 env steps (5 physics steps each):
- "uniform": i.i.d. uniform actions in [-1, 1]^8 every step;
- "bang-bang hold H": every H env steps, each motor gets -1 or +1 at random (the extreme,
  sustained torques that an action-sequence optimiser tends to pick).
It reports, per variant and action process, the share of steps spent on the back (torso z axis
pointing down: 1 - 2 (qx^2 + qy^2) < 0), how many episodes tipped over at all, and the median
step of the first tip (1,000 = never).

    python experiments/ant_flips.py [--episodes 24] [--out experiments/results/ant_flips.json]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import mujoco
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from dscpp_jax import envs  # noqa: E402
from dscpp_jax.envs.ant_maze import AntConfig, ant_mjcf  # noqa: E402

VARIANTS = {
    # the env before soft contacts: MuJoCo's default solimp, explicit joint damping
    "stiff contacts, Euler (explicit damping)": dict(contact_solimp="0.9 0.95 0.001",
                                                     eulerdamp=False),
    "soft contacts, Euler (implicit damping): default": dict(),
    "soft contacts, RK4": dict(integrator="RK4"),
    "D4RL: soft contacts, 1 cm margin, RK4": dict(integrator="RK4", contact_margin=0.01),
    # cheaper candidates for RK4's steadiness (same 0.1 s per env step)
    "soft contacts, implicitfast": dict(integrator="implicitfast"),
    "soft contacts, Euler, 0.01 s x 10": dict(timestep=0.01, frame_skip=10),
    "soft contacts, implicitfast, 0.01 s x 10": dict(integrator="implicitfast", timestep=0.01,
                                                     frame_skip=10),
}
PROCESSES = {"uniform": 0, "bang-bang hold 1": 1, "bang-bang hold 3": 3, "bang-bang hold 10": 10}


def run(xml: str, hold: int, episodes: int, steps: int, seed: int, frame_skip: int = 5) -> dict:
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(seed)
    back_share, first = [], []
    for _ in range(episodes):
        mujoco.mj_resetData(m, d)
        d.qpos[:] = m.qpos0 + rng.uniform(-0.1, 0.1, m.nq)
        d.qpos[3:7] /= np.linalg.norm(d.qpos[3:7])
        d.qvel[:] = 0.1 * rng.normal(size=m.nv)
        a = np.zeros(m.nu)
        tip, on_back = steps, 0
        for t in range(steps):
            if hold == 0:
                a = rng.uniform(-1.0, 1.0, m.nu)
            elif t % hold == 0:
                a = rng.choice([-1.0, 1.0], m.nu)
            d.ctrl[:] = a
            for _ in range(frame_skip):
                mujoco.mj_step(m, d)
            q = d.qpos[3:7]
            if 1.0 - 2.0 * (q[1] ** 2 + q[2] ** 2) < 0.0:
                on_back += 1
                tip = min(tip, t)
        back_share.append(on_back / steps)
        first.append(tip)
    return {"share_of_steps_on_back": float(np.mean(back_share)),
            "episodes_tipped": int(sum(f < steps for f in first)), "episodes": episodes,
            "median_first_tip_step": float(np.median(first))}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=24)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="experiments/results/ant_flips.json")
    args = p.parse_args(argv)
    layout = envs.make("u_maze").layout
    results = {"mujoco": mujoco.__version__, "episodes": args.episodes, "steps": args.steps,
               "seed": args.seed, "variants": {}}
    print(f"{'variant':50s} {'actions':18s} {'on back':>8s} {'tipped':>8s} {'first tip':>9s}")
    for name, kw in VARIANTS.items():
        cfg = AntConfig(**kw)
        xml = ant_mjcf(layout, cfg)
        results["variants"][name] = {"config": kw, "results": {}}
        for proc, hold in PROCESSES.items():
            t0 = time.time()
            r = run(xml, hold, args.episodes, args.steps, args.seed, cfg.frame_skip)
            r["seconds"] = round(time.time() - t0, 1)
            results["variants"][name]["results"][proc] = r
            print(f"{name:50s} {proc:18s} {r['share_of_steps_on_back']:8.2f} "
                  f"{r['episodes_tipped']:4d}/{args.episodes:<3d} {r['median_first_tip_step']:9.0f}",
                  flush=True)
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=2)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
