"""Does the paper's ordering of the exploration settings depend on the scale? Mixed against DDPG+BC
at several environment counts per iteration, the same updates at each.

Train one run per environment count (both settings and 3 seeds in one program each), then report:

    for n in 5 32 128 512; do
        python -m regrasp_mjx.train --preset paper --exploration mixed,ddpg_bc --seeds 3 \\
            --set num_envs=$n --set epochs=60 --demos runs/demos --out runs/scale/envs$n
    done
    python experiments/scale.py --run 5=runs/scale/envs5 --run 32=runs/scale/envs32 \\
        --run 128=runs/scale/envs128 --run 512=runs/scale/envs512 --out experiments/results/scale

Writes ``scale.md``/``scale.json`` (per environment count and setting: the bare test success at the
last epoch and the mean of the last ten epochs, mean ± std over seeds, and mixed minus DDPG+BC with
its spread over the paired seeds) and ``scale.png`` (success against environments, mean and range).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from regrasp_mjx import analysis
from regrasp_mjx.atomic import write_figure, write_results

SETTINGS = ("mixed", "ddpg_bc")
LABEL = {"mixed": "DDPG+BC (mixed)", "ddpg_bc": "DDPG+BC"}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", action="append", required=True, metavar="ENVS=FOLDER")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    data: dict[int, dict[str, dict[str, list[float]]]] = {}
    for item in args.run:
        envs, _, folder = item.partition("=")
        log_path = Path(folder) / "log.jsonl"
        data[int(envs)] = {}
        for setting in SETTINGS:
            log = analysis.read_log(log_path, setting)
            _, success = analysis.seed_band(log, "test.success_rate")
            data[int(envs)][setting] = {
                "seeds": sorted(log),
                "last": success[:, -1].tolist(),
                "last10": success[:, -10:].mean(1).tolist(),
                "epochs": int(next(iter(log.values()))["epoch"][-1]),
            }
    ms = lambda xs: f"{np.mean(xs):.3f} ± {np.std(xs):.3f}"  # noqa: E731
    lines = [
        "Bare test success on paper300 (mean ± std over seeds); mixed - DDPG+BC over paired seeds.",
        "",
        "| environments per iteration | epochs | DDPG+BC (mixed), last 10 epochs | DDPG+BC, last 10 epochs | mixed - DDPG+BC |",
        "| ---: | ---: | --- | --- | --- |",
    ]
    for envs in sorted(data):
        m, d = data[envs]["mixed"], data[envs]["ddpg_bc"]
        diff = np.array(m["last10"]) - np.array(d["last10"])
        lines.append(f"| {envs} | {m['epochs']} | {ms(m['last10'])} | {ms(d['last10'])} | {ms(diff)} |")
    print("\n".join(lines))
    write_results(args.out, "scale", lines, {str(k): v for k, v in data.items()})

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    xs = np.array(sorted(data))
    for setting, colour in zip(SETTINGS, ("tab:green", "tab:blue")):
        vals = [np.array(data[x][setting]["last10"]) for x in xs]
        ax.plot(xs, [v.mean() for v in vals], marker="o", color=colour, label=LABEL[setting])
        ax.fill_between(xs, [v.min() for v in vals], [v.max() for v in vals], color=colour, alpha=0.2)
    ax.axhline(0.97, color="grey", ls="--", lw=0.8, label="paper: mixed 0.97")
    ax.axhline(0.71, color="grey", ls=":", lw=0.8, label="paper: DDPG+BC 0.71")
    ax.set_xscale("log")
    ax.set_xlabel("environments per iteration (same updates)")
    ax.set_ylabel("test success, mean of the last 10 epochs (bare)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    write_figure(Path(args.out) / "scale.png", fig, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
