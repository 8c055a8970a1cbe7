"""Success of several policies on paper300 and on held-out problems, bare and shielded.

    python experiments/policies.py --policy "student=runs/x/student/policy" --policy "shipped=" \\
        --heldout 3000:2022 --out experiments/results/policies --name policies

Each policy is planned through ``Policy.plan`` (as deployed) on the committed test set and on a
held-out set drawn here from its own seed, once without the
collision shield (``bare``: the network alone) and once with it. Writes ``NAME.md`` and
``NAME.json``. With ``--no-paper300`` and a validation seed of its own it picks a policy without
touching a test set. Timings are not taken here: time one query on one core with
``JAX_PLATFORMS=cpu taskset -c 0 python -m regrasp_mjx.evaluate --json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import jax

from regrasp_mjx import host
from regrasp_mjx.atomic import write_results
from regrasp_mjx.config import parse_overrides
from regrasp_mjx.evaluate import DEFAULT_TESTSET, episode_poses, outcomes
from regrasp_mjx.policy import load_policy
from regrasp_mjx.sampling import load_testset
from regrasp_mjx.scene import load_scene
from regrasp_mjx.testset import make_testset


def valid_at_margin(episodes, env_config):
    """The problems whose start and goal keep ``env_config.clearance_mm`` (as
    ``experiments/clearance.py`` counts them): the others fail before a step is taken."""
    gate = host.HostChecker(scene=load_scene(env_config.scene), clearance_mm=env_config.clearance_mm)
    keep = gate.clear_problems(*episode_poses(episodes))
    return type(episodes)(**{f.name: getattr(episodes, f.name)[keep] for f in dataclasses.fields(episodes)})


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--policy", action="append", required=True, metavar="NAME=FOLDER", help="empty FOLDER: shipped")
    p.add_argument(
        "--heldout", action="append", default=None, help="N:SEED of a set drawn here (repeatable; default 3000:2022)"
    )
    p.add_argument("--no-paper300", action="store_true", help="leave the committed test set out (e.g. to select)")
    p.add_argument(
        "--env",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="plan every policy in this changed environment (Policy.with_env), e.g. scene.conservative_needle=True "
        "or clearance_mm=0.1; with a margin, problems whose start or goal is already within it are left out",
    )
    p.add_argument("--out", default=None)
    p.add_argument("--name", default="policies")
    args = p.parse_args(argv)
    changes = parse_overrides(args.env)
    policies = {}
    for item in args.policy:
        name, _, folder = item.partition("=")
        policy = load_policy(folder or None)
        policies[name] = (folder or "shipped", policy.with_env(**changes) if changes else policy)
    env_config = next(iter(policies.values()))[1].env_config
    sets = {} if args.no_paper300 else {"paper300": load_testset(DEFAULT_TESTSET)[0]}
    for spec in args.heldout or ["3000:2022"]:
        n, seed = (int(x) for x in spec.split(":"))
        sets[f"held-out {n} (seed {seed})"] = make_testset(n, seed, env_config)
    if env_config.clearance_mm > 0:
        sets = {k: valid_at_margin(v, env_config) for k, v in sets.items()}
    rows = []
    for name, (folder, policy) in policies.items():
        for sname, episodes in sets.items():
            for r in outcomes(policy, episodes).values():
                rows.append(
                    {
                        "policy": name,
                        "folder": folder,
                        "hidden": policy.contract["network"]["hidden"],
                        "members": policy.members,
                        "testset": sname,
                        "env": changes,
                        **r,
                    }
                )
                print(json.dumps(rows[-1]), flush=True)
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    lines = [
        f"Machine: {jax.default_backend()} ({jax.devices()[0].device_kind}); planned through Policy.plan.",
        "",
        "| policy | network | test set | rollout | success | collision | time-out | path (mm) | steps |",
        "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        net = f"{r['members']} x " if r["members"] > 1 else ""
        net += "x".join(str(h) for h in r["hidden"])
        lines.append(
            f"| {r['policy']} | {net} | {r['testset']} | {r['rollout']} | {r['success_rate']:.3f} | "
            f"{r['collision_rate']:.3f} | {r['time_out_rate']:.3f} | {fmt(r['path_length_mm'])} | {fmt(r['steps'])} |"
        )
    print("\n".join(lines))
    write_results(args.out, args.name, lines, rows)


if __name__ == "__main__":
    main()
