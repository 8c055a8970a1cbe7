"""A trained policy (improved by lookahead) DAgger-distilled into one network: :func:`distill`, what
``python -m regrasp_mjx.distill`` and a training run with ``distill.iterations`` > 0 call.

The teacher is any policy (one network or an ensemble); see :mod:`regrasp_mjx.agents.dagger` for
what the teacher does and how the student learns. Each iteration prints a line (student's bare
success on the validation and test problems, the share of visited states where the teacher overrode
its policy, the loss, the ETA) and appends a row to ``OUT/distill_log.jsonl``. ``OUT/policy`` is the
student of the iteration best on validation (its own seed, never the test set), ``OUT/policy_last``
the last; ``OUT/distill_eval.json`` holds the teacher's and the exported student's test-set numbers,
bare and shielded. :data:`DISTILL_OUTPUTS` names what a distillation writes into ``OUT``.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp

from regrasp_mjx.agents.dagger import DistillConfig, Distiller, aim
from regrasp_mjx.core.atomic import write_json
from regrasp_mjx.core.host_loop import BestOf, Phases, RunLog, eta
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.estimates import evaluate_noisy
from regrasp_mjx.envs.rollout import evaluate_actor, summarize
from regrasp_mjx.inference.policy import Policy, load_policy, mean_action, save_policy
from regrasp_mjx.inference.testset_plans import outcomes
from regrasp_mjx.world.sampling import Episode
from regrasp_mjx.world.testsets import make_testset

VALIDATION_SEED = 2_000_003  # + the distillation seed; the learner's validation problems use 1_000_003 + seed


def distill(
    teacher: Policy,
    out: Path,
    cfg: DistillConfig,
    testset: Episode,
    teacher_name: str = "",
    quiet: bool = False,
    precompile: bool = False,
) -> dict[str, Any]:
    """Distils ``teacher`` into a student in ``out`` (see the module docstring); returns the
    contents of ``distill_eval.json``. ``precompile``: stop after the first iteration and its
    evaluations, still exporting and testing the student as the end does, so every program of this
    distillation has run once and sits in the compilation cache (an untrained teacher of the same
    shape compiles the same programs); writes ``precompile.json`` instead of ``distill_eval.json``."""

    log = (lambda msg: None) if quiet else (lambda msg: print(msg, flush=True))
    env_cfg = teacher.env_config
    env = RegraspEnv(env_cfg)
    aimed = aim(env_cfg, cfg)  # the student learns to reach deeper into the goal; it is judged as always
    distiller = Distiller(RegraspEnv(aimed) if aimed != env_cfg else env, teacher.network(), cfg)
    valset = make_testset(cfg.validation_size, VALIDATION_SEED + cfg.seed, env_cfg)
    f32 = lambda tree: jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), tree)  # noqa: E731
    val, test = f32(valset), f32(testset)

    @jax.jit
    def student_eval(params, normalizer, episodes):
        return evaluate_actor(env, functools.partial(distiller.nets.policy, params, normalizer), episodes)

    # the seed's key, the weights and the problems are arguments: the students of a recipe (three
    # teachers, three seeds) share these programs through the persistent compilation cache
    @jax.jit
    def student_eval_noisy(params, normalizer, episodes, key):
        act = functools.partial(distiller.nets.policy, params, normalizer)
        return evaluate_noisy(env, act, episodes, key, cfg.obs_noise_mm, cfg.obs_bias_mm, cfg.obs_tool_noise_mm)

    noisy_key = jax.random.PRNGKey(VALIDATION_SEED + cfg.seed)
    apply, weights = teacher.network()
    teacher_eval = jax.jit(lambda w, episodes: evaluate_actor(env, lambda obs: mean_action(apply(w, obs)), episodes))
    t0 = time.perf_counter()
    teacher_val = summarize(jax.device_get(teacher_eval(weights, val)), "bare")
    log(
        f"teacher {teacher_name or '(given)'}: {teacher.members} network(s), bare success on "
        f"{cfg.validation_size} validation problems {teacher_val['success_rate']:.3f}"
    )
    out.mkdir(parents=True, exist_ok=True)
    run_log = RunLog(out / "distill_log.jsonl")
    run_log.path.unlink(missing_ok=True)  # a distillation starts anew
    ds = distiller.init()
    best, compile_s, phases = BestOf.fresh(1), None, Phases()
    training = {
        "teacher": teacher_name,
        "teacher_training": teacher.contract.get("training"),
        "distill": dataclasses.asdict(cfg),
    }
    save = lambda folder, ds, extra: save_policy(  # noqa: E731
        folder, ds.params, ds.normalizer, cfg.hidden, env_cfg, extra={"training": {**training, **extra}}
    )
    for it in range(1 if precompile else cfg.iterations):
        t_it = time.perf_counter()
        if it == 0:  # the first iteration compiles its programs: tens of seconds on a CPU without a line
            log("distillation: compiling the iteration and evaluation programs (once per process) ...")
        with phases("iterations"):
            ds, metrics = distiller.iteration(ds, it == 0)
            metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
        if compile_s is None:  # one program for every iteration: the first compiles it
            compile_s = time.perf_counter() - t0
        with phases("evaluate"):
            va = summarize(jax.device_get(student_eval(ds.params, ds.normalizer, val)), "bare")
            te = summarize(jax.device_get(student_eval(ds.params, ds.normalizer, test)), "bare")
            # with noise the student is chosen under the noise it learned (one new frame a step, bare)
            vn = (
                summarize(jax.device_get(student_eval_noisy(ds.params, ds.normalizer, val, noisy_key)), "noisy")
                if distiller.noisy
                else None
            )
        if best.update([(vn or va)["success_rate"]], it + 1):
            with phases("export"):
                save(
                    out / "policy",
                    ds,
                    {
                        "iteration": it + 1,
                        "validation_success": va["success_rate"],
                        "validation_noisy_success": vn and vn["success_rate"],
                    },
                )
        row = {
            "stage": "distill",
            "iteration": it + 1,
            "validation": va,
            "validation_noisy": vn,
            "test": te,
            **metrics,
            "iteration_s": time.perf_counter() - t_it,
            "wall_s": time.perf_counter() - t0,
            "timing": phases.take(),
        }
        run_log.write([row], step_key="iteration")
        log(
            f"distill {it + 1}/{cfg.iterations}  val success {va['success_rate']:.3f}"
            + (f" (noisy {vn['success_rate']:.3f})" if vn else "")
            + f"  test success {te['success_rate']:.3f} (collision {te['collision_rate']:.3f})  "
            f"rollouts {metrics['rollout_success']:.3f}  "
            f"overridden {metrics['overridden']:.3f}  teacher reaches {metrics['teacher_reaches']:.3f}  "
            f"loss {metrics['loss']:.5f}  {row['iteration_s']:.1f} s/it  {eta(it + 1, cfg.iterations, row['wall_s'])}"
        )
    save(out / "policy_last", ds, {"iteration": it + 1})
    final = {
        "teacher": teacher_name,
        "teacher_validation": teacher_val,
        "teacher_test": outcomes(teacher, testset),
        "student": str(out / "policy"),
        "best_iteration": best.step[0],
        "best_validation_success": best.score[0],
        "test": outcomes(load_policy(out / "policy"), testset),
        "hidden": list(cfg.hidden),
        "compile_s": compile_s,
        "wall_s": time.perf_counter() - t0,
    }
    if precompile:
        write_json(out / "precompile.json", {**final, "precompile": True})
        log(f"precompiled this distillation's programs in {final['wall_s']:.0f} s (one iteration; {out})")
        return final
    write_json(out / "distill_eval.json", final)
    st, tt = final["test"], final["teacher_test"]
    log(
        f"student (iteration {best.step[0]}, best on validation) on the test set: "
        f"bare {st['bare']['success_rate']:.3f}, shielded {st['shielded']['success_rate']:.3f}; "
        f"teacher bare {tt['bare']['success_rate']:.3f}, shielded {tt['shielded']['success_rate']:.3f}"
    )
    return final


# what a distillation writes into OUT: an earlier one's is refused without --overwrite
DISTILL_OUTPUTS = ("distill_log.jsonl", "policy", "policy_last", "distill_eval.json", "precompile.json")
