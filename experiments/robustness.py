"""The robustness table (``regrasp_mjx.robustness``) for several policies: frame noise, bias and
clearance margins; open loop, per-frame and fused closed loop; judged on the true needle.

    python experiments/robustness.py --out experiments/results/robustness          # every shipped policy
    python experiments/robustness.py --policy a=runs/x/policy --heldout 1000:7000001 --name select
    python experiments/robustness.py --merge part0.json part1.json --out experiments/results/robustness
    python experiments/robustness.py --docs experiments/results/robustness/robustness.json

``--docs`` rewrites the generated robustness blocks of README.md, docs/results.md and
experiments/RESULTS.md (``regrasp_mjx.robustness.docs_blocks``: the default and ``exact``) from a
table file; run it whenever the table is made again (tests/test_robustness.py checks they agree).

Each policy runs on its own test set (paper300 for a paper-task policy, general1000 for a general
one) unless ``--testset`` or ``--heldout N:SEED`` (problems drawn here from that seed: validation
problems to choose a policy on, never a test set) names the problems. ``NAME.json`` records each
policy's hash (``robustness.policy_hash``), so a test can tell when a shipped policy changed after
its table was made.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax

from regrasp_mjx import robustness
from regrasp_mjx.atomic import write_results, write_text
from regrasp_mjx.policy import load_policy, shipped_policies
from regrasp_mjx.sampling import load_testset
from regrasp_mjx.testset import make_testset


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--policy", action="append", metavar="NAME=FOLDER", help="repeatable; default: every shipped policy")
    p.add_argument("--testset", default=None, help="a shipped name or .npz for every policy (default: each one's own)")
    p.add_argument("--heldout", default=None, metavar="N:SEED", help="problems drawn from this seed instead")
    p.add_argument("--modes", default=",".join(robustness.MODES), help=f"comma-separated of {list(robustness.MODES)}")
    p.add_argument("--conditions", default=None, help="comma-separated condition names (default: all rows)")
    p.add_argument("--seed", type=int, default=0, help="seed of the needle-estimate noise")
    p.add_argument("--out", default=None)
    p.add_argument("--name", default="robustness")
    p.add_argument("--merge", nargs="+", metavar="JSON", help="only join the tables of earlier runs (in this order)")
    p.add_argument("--docs", metavar="JSON", help="only rewrite the docs' robustness blocks from this table file")
    args = p.parse_args(argv)
    if args.docs:
        return write_docs(args.docs)
    if args.merge:
        return merge(args.merge, args.out, args.name)
    modes = tuple(args.modes.split(","))
    conditions = robustness.CONDITIONS
    if args.conditions:
        wanted = args.conditions.split(",")
        conditions = tuple(c for c in conditions if c.name in wanted)
    specs = [item.partition("=")[::2] for item in args.policy] if args.policy else [(n, n) for n in shipped_policies()]
    meta = {"backend": jax.default_backend(), "device": jax.devices()[0].device_kind, "seed": args.seed, "modes": modes}
    tables, lines = (
        [],
        [f"Machine: {jax.default_backend()} ({jax.devices()[0].device_kind}); shielded; seed {args.seed}.", ""],
    )
    for name, folder in specs:
        policy = load_policy(folder)
        if args.heldout:
            n, seed = (int(x) for x in args.heldout.split(":"))
            episodes, problems = make_testset(n, seed, policy.env_config), f"held-out {n} (seed {seed})"
        else:
            problems = args.testset or ("general1000" if policy.general else "paper300")
            episodes = load_testset(problems)[0]
        print(f"{name} ({folder}) on {problems}", flush=True)
        t0 = time.perf_counter()
        rows = robustness.table(policy, episodes, modes, args.seed, conditions, log=print)
        tables.append(
            {
                "policy": name,
                "folder": folder,
                "policy_hash": robustness.policy_hash(folder),
                "hidden": policy.contract["network"]["hidden"],
                "problems": problems,
                "wall_s": time.perf_counter() - t0,
                "machine": f"{meta['backend']} ({meta['device']})",
                "seed": args.seed,
                "rows": rows,
            }
        )
        lines += [
            f"**{name}** (`{folder}`, {'x'.join(map(str, tables[-1]['hidden']))}, hash {tables[-1]['policy_hash']}) on {problems}:",
            "",
        ]
        lines += robustness.markdown(rows, modes) + [""]
        write_results(args.out, args.name, lines, {**meta, "tables": tables})  # after each policy: a cut run keeps them
    print("\n".join(lines))
    print(json.dumps({"out": args.out, "name": args.name}))


def merge(paths: list[str], out: str | None, name: str) -> None:
    """One table file from the tables of several runs (e.g. parts run side by side on one GPU); the
    parts of one policy (same hash, e.g. its noise rows and its margin rows run apart) become one
    table, rows in :data:`robustness.CONDITIONS` order."""
    by_policy: dict[str, dict] = {}
    for path in paths:
        data = json.loads(Path(path).read_text())
        for t in data["tables"]:
            if "machine" not in t:  # a part run before the tables carried their machine
                t = {**t, "machine": f"{data['backend']} ({data['device']})", "seed": data["seed"]}
            seen = by_policy.get(t["policy"])
            if seen is None:
                by_policy[t["policy"]] = {**t, "rows": list(t["rows"])}
                continue
            if seen["policy_hash"] != t["policy_hash"] or seen["problems"] != t["problems"]:
                raise SystemExit(f"{path}: {t['policy']} was measured with another policy file or problems than before")
            seen["rows"] += t["rows"]
            seen["wall_s"] = seen.get("wall_s", 0.0) + t.get("wall_s", 0.0)
            if t["machine"] not in seen["machine"]:
                seen["machine"] += f"; {t['machine']}"
    order = {c.name: i for i, c in enumerate(robustness.CONDITIONS)}
    tables, lines = [], []
    for t in by_policy.values():
        t["rows"].sort(key=lambda r: order.get(r["condition"], len(order)))
        tables.append(t)
        lines += [
            f"**{t['policy']}** (`{t['folder']}`, {'x'.join(map(str, t['hidden']))}, hash {t['policy_hash']}) on "
            f"{t['problems']}; {t['machine']}:",
            "",
        ]
        modes = tuple(m for m in robustness.MODES if any(r["mode"] == m for r in t["rows"]))
        lines += robustness.markdown(t["rows"], modes) + [""]
    print("\n".join(lines))
    write_results(out, name, lines, {"tables": tables})


ROOT = Path(__file__).resolve().parents[1]
DOC_PAGES = {  # page -> the blocks it holds
    ROOT / "README.md": ("summary",),
    ROOT / "docs" / "results.md": ("summary",),
    ROOT / "experiments" / "RESULTS.md": ("tables",),
}


def write_docs(table_file: str) -> None:
    """The docs' robustness blocks from ``table_file`` (this script's JSON), each page written atomically."""
    blocks = robustness.docs_blocks(json.loads(Path(table_file).read_text())["tables"])
    for page, kinds in DOC_PAGES.items():
        text = page.read_text()
        for kind in kinds:
            text = robustness.replace_block(text, kind, blocks[kind])
        write_text(page, text)
        print(f"rewrote {page.relative_to(ROOT)} ({', '.join(kinds)})")


if __name__ == "__main__":
    main()
