"""``python -m regrasp_mjx.export_onnx``: the actor (normaliser, MLP, tanh, ensemble mean) as ONNX.

    python -m regrasp_mjx.export_onnx --out policy.onnx [--policy runs/fast/policy]

Input ``obs`` float32 ``[B, 21]`` (``[B, 37]`` for a general policy; B dynamic; the layout in
``policy.json``), output ``action``
float32 ``[B, 6]`` in [-1, 1]. The robot side then applies the action as ``policy.json`` says
(or plans with :meth:`regrasp_mjx.inference.policy.Policy.plan`, which also checks collisions). Converted
with jax2onnx; ``check`` runs it in ONNX Runtime against JAX on random observations.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from regrasp_mjx.core.atomic import atomic_write, dumps, output_file_problem
from regrasp_mjx.core.host_loop import run_command
from regrasp_mjx.inference.policy import DEFAULT_POLICY, Policy, PolicyError, load_policy, shipped_policies


def export_onnx(policy: Policy, path: str | os.PathLike) -> Path:
    """Writes the policy's actor to ``path`` (ONNX, opset 17+); returns the path."""
    from jax2onnx import to_onnx  # optional (the onnx extra)

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model = to_onnx(
        policy.actor_fn(),
        [("B", policy.obs_size)],
        model_name="regrasp_actor",
        input_names=["obs"],
        output_names=["action"],
    )
    atomic_write(path, lambda f: f.write(model.SerializeToString()))
    return path


def check(policy: Policy, path: str | os.PathLike, n: int = 1000, seed: int = 0) -> float:
    """Largest absolute difference between ONNX Runtime's and JAX's actions on ``n`` observations
    drawn around the policy's normaliser statistics."""
    import onnxruntime as ort  # optional (the onnx extra)

    rng = np.random.default_rng(seed)
    mean = np.asarray(policy.normalizer.mean)[0]
    std = np.asarray(policy.normalizer.std)[0]
    obs = (mean + std * rng.standard_normal((n, policy.obs_size)) * 2.0).astype(np.float32)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (onnx_actions,) = session.run(["action"], {"obs": obs})
    return float(np.max(np.abs(onnx_actions - policy.act(obs))))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m regrasp_mjx.export_onnx", description=__doc__.splitlines()[0])
    p.add_argument(
        "--policy",
        default=None,
        help=f"policy folder, or a shipped name ({', '.join(shipped_policies())}; "
        f"default: the shipped one, {DEFAULT_POLICY})",
    )
    p.add_argument("--out", required=True, help="the .onnx file to write")
    p.add_argument("--no-check", action="store_true", help="skip the ONNX Runtime comparison")
    args = p.parse_args(argv)
    problem = output_file_problem(args.out, ".onnx")
    if problem:
        p.error(problem)
    try:
        policy = load_policy(args.policy)
    except PolicyError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    out = export_onnx(policy, args.out)
    result = {"out": str(out), "bytes": out.stat().st_size}
    if not args.no_check:
        result["max_abs_diff_vs_jax"] = check(policy, out)
    print(dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(run_command(main, "the .onnx file is written whole or not at all: run the same command again"))
