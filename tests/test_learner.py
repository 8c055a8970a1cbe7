"""DDPG+BC: losses by hand, the Q-filter, schedules, target cadence, a tiny problem learned,
exact resume, and exported policies."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from regrasp_mjx.agents.dagger import DistillConfig
from regrasp_mjx.agents.ddpg_bc import checkpoint, losses
from regrasp_mjx.agents.ddpg_bc.config import EXPLORATION, PAPER_LEARNER, Exploration, TrainConfig, make_config
from regrasp_mjx.agents.ddpg_bc.learner import Learner
from regrasp_mjx.core.config import ConfigError, EnvConfig, SceneConfig
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.estimates import NeedleNoise
from regrasp_mjx.inference.policy import PolicyError, load_policy, save_policy
from regrasp_mjx.planning.episodes import make_replay, replay_paths, save_demos
from regrasp_mjx.planning.ompl_planner import PlannerConfig
from regrasp_mjx.planning.pool import PlannerPool
from regrasp_mjx.world.testsets import make_testset

# ---- losses by hand ---------------------------------------------------------------------------
# Linear stand-ins for the networks: pi(p, o) = p * o[:, :1], Q(p, o, a) = p * (o[:, 0] + a[:, 0]).
POLICY = lambda p, o: p * o[:, :1]  # noqa: E731
Q = lambda p, o, a: p * (o[:, 0] + a[:, 0])  # noqa: E731
BATCH = {
    "obs": jnp.array([[1.0, 0.0], [2.0, 0.0]]),
    "action": jnp.array([[0.5], [-1.0]]),
    "reward": jnp.array([-0.02, 1.0]),
    "next_obs": jnp.array([[1.0, 0.0], [3.0, 0.0]]),
    "terminal": jnp.array([0.0, 1.0]),
}


def test_critic_loss_by_hand():
    # Target actor 0.5: a' = [0.5, 1.5]; target critic 0.2: Q' = [0.2 * 1.5, 0.2 * 4.5] = [0.3, 0.9].
    # y = [-0.02 + 0.5 * 0.3, 1 + 0] = [0.13, 1.0]; Q(s, a) with critic 1 = [1.5, 1.0].
    # loss = ((1.5 - 0.13)^2 + 0) / 2 = 0.93845.
    loss, m = losses.critic_loss(1.0, 0.5, 0.2, BATCH, POLICY, Q, gamma=0.5)
    assert float(loss) == pytest.approx(0.93845, abs=1e-6)
    assert float(m["q_target"]) == pytest.approx((0.13 + 1.0) / 2, abs=1e-6)
    # The target is clipped to [-1/(1-gamma), 1]: reward 1 with a bootstrapped 0.9 gives 1.45 -> 1.
    clipped = {**BATCH, "reward": jnp.array([1.0, 1.0]), "terminal": jnp.array([0.0, 0.0])}
    _, m = losses.critic_loss(1.0, 0.5, 0.2, clipped, POLICY, Q, gamma=0.5)
    assert float(m["q_target"]) == pytest.approx(1.0, abs=1e-6)


def test_actor_loss_by_hand():
    # Actor 1: pi = [1, 2]. Critic -1: Q(s, pi) = [-2, -4]; Q(s, a_demo) = [-1.5, -1.0].
    # primary = 0.1 * (-mean(-2, -4) + 1 * mean(1, 4)) = 0.1 * (3 + 2.5) = 0.55.
    # Only sample 2 is a demonstration and -1.0 > -4 keeps it: bc = 0.01 * (2 - (-1))^2 = 0.09.
    is_demo = jnp.array([False, True])
    loss, m = losses.actor_loss(1.0, -1.0, BATCH, is_demo, POLICY, Q, prm_coef=0.1, bc_coef=0.01, action_l2=1.0)
    assert float(m["primary_loss"]) == pytest.approx(0.55, abs=1e-6)
    assert float(m["bc_loss"]) == pytest.approx(0.09, abs=1e-6)
    assert float(loss) == pytest.approx(0.64, abs=1e-6)


# Two linear critics (ours, TD3's clipped double Q): Q_k(p, o, a) = p[k] * (o[:, 0] + a[:, 0]).
Q2 = lambda p, o, a: p[:, None] * (o[:, 0] + a[:, 0])[None]  # noqa: E731


def test_twin_critics_take_the_minimum_target_and_both_regress_on_it():
    # Target critics [0.2, 0.4] at a' = [0.5, 1.5]: Q' = [[0.3, 0.9], [0.6, 1.8]], min [0.3, 0.9], so the
    # targets are those of the one-critic case, y = [0.13, 1.0]. Critics [1, 2]: Q(s, a) = [[1.5, 1.0],
    # [3.0, 2.0]]; loss = ((1.5 - 0.13)^2 + 0) / 2 + ((3 - 0.13)^2 + (2 - 1)^2) / 2 = 0.93845 + 4.61845.
    loss, m = losses.critic_loss(jnp.array([1.0, 2.0]), 0.5, jnp.array([0.2, 0.4]), BATCH, POLICY, Q2, gamma=0.5)
    assert float(loss) == pytest.approx(5.5569, abs=1e-5)
    assert float(m["q_target"]) == pytest.approx((0.13 + 1.0) / 2, abs=1e-6)
    assert float(m["q"]) == pytest.approx(1.25, abs=1e-6)  # the first critic's mean
    # The actor and the Q-filter use the first critic: critics [-1, 5] give the one-critic numbers.
    is_demo = jnp.array([False, True])
    _, a = losses.actor_loss(
        1.0, jnp.array([-1.0, 5.0]), BATCH, is_demo, POLICY, Q2, prm_coef=0.1, bc_coef=0.01, action_l2=1.0
    )
    assert float(a["primary_loss"]) == pytest.approx(0.55, abs=1e-6) and float(a["bc_loss"]) == pytest.approx(
        0.09, abs=1e-6
    )


def test_layer_norm_critic_normalises_every_hidden_layer():
    # A layer norm after each hidden ReLU makes the critic blind to a positive rescaling of the layer
    # before it (and of its bias): scaling the first layer by 7 changes no estimate. Without layer
    # norm the ReLU network is positively homogeneous in that layer, so the estimate moves.
    from regrasp_mjx.agents.ddpg_bc.networks import init_params, make_networks

    for layer_norm in (True, False):
        nets = make_networks(2, (8, 8), critics=2, critic_layer_norm=layer_norm)
        _, critic = init_params(nets, jax.random.PRNGKey(0), 3, 2)
        names = sorted(critic["params"])
        assert names == (["LayerNorm_0", "LayerNorm_1"] if layer_norm else []) + ["hidden_0", "hidden_1", "hidden_2"]
        x = jax.random.normal(jax.random.PRNGKey(1), (4, 5))
        apply = lambda p, nets=nets, x=x: jax.vmap(nets.critic.apply, in_axes=(0, None))(p, x)  # noqa: E731
        scaled = jax.tree_util.tree_map_with_path(
            lambda path, v: v * 7.0 if "hidden_0" in jax.tree_util.keystr(path) else v, critic
        )
        same = np.allclose(apply(critic), apply(scaled), atol=1e-4)
        assert same == layer_norm
    with pytest.raises(ConfigError, match="critic_layer_norm=1 is not accepted"):
        make_config("smoke", critic_layer_norm=1)


def test_target_policy_noise_is_clipped():
    # std 10 with clip 0.1: the target action of row 1 (0.5) moves by exactly +-0.1, so its target is
    # -0.02 + 0.5 * 0.2 * (1 + 0.5 +- 0.1) = 0.13 +- 0.01; row 2 is terminal (1.0).
    targets = set()
    for k in range(8):
        _, m = losses.critic_loss(1.0, 0.5, 0.2, BATCH, POLICY, Q, 0.5, jax.random.PRNGKey(k), 10.0, 0.1)
        targets.add(round(float(m["q_target"]) * 2 - 1.0, 6))
    assert targets == {0.12, 0.14}


def test_q_filter_keeps_exactly_the_demos_the_critic_prefers():
    q_demo = jnp.array([1.0, 0.2, 0.5, 0.9, -1.0])
    q_pi = jnp.array([0.5, 0.3, 0.5, 0.1, -2.0])
    is_demo = jnp.array([True, True, True, False, True])
    np.testing.assert_array_equal(np.asarray(losses.q_filter(q_demo, q_pi, is_demo)), [1, 0, 0, 0, 1])


# ---- schedules and config ----------------------------------------------------------------------
def test_exploration_schedules():
    mixed = EXPLORATION["mixed"]
    assert mixed.at(0) == pytest.approx((0.3, 0.1))
    assert mixed.at(100) == pytest.approx((0.3 - 0.06, 0.1 + 0.45))
    assert mixed.at(200) == pytest.approx((0.18, 1.0))  # E_T caps at 1
    assert mixed.at(1000) == pytest.approx((0.0, 1.0))  # E_R floors at 0
    assert EXPLORATION["ddpg_bc"].at(50) == pytest.approx((0.27, 0.0))
    assert EXPLORATION["targeted"].at(0) == EXPLORATION["targeted"].at(999) == pytest.approx((0.02, 0.5))


def test_grow_with_devices_keeps_each_devices_share_and_scales_the_learning_rate_by_sqrt():
    from regrasp_mjx.agents.ddpg_bc.config import grow_with_devices, make_config

    base = make_config("fast")
    two = grow_with_devices(base, 2)
    assert (two.num_envs, two.batch_size, two.buffer_size, two.demo_chunk) == (1024, 512, 2_000_000, 1024)
    assert (two.online_batch, two.demo_batch) == (2 * base.online_batch, 2 * base.demo_batch)  # 384 + 128
    assert two.lr_actor == pytest.approx(1e-4 * 2**0.5) and two.lr_critic == pytest.approx(1e-4 * 2**0.5)
    assert (two.devices, two.shard, two.epochs, two.updates_per_iteration) == (2, "envs", 60, 200)
    assert grow_with_devices(base, 1) == dataclasses.replace(base, shard="envs")
    with pytest.raises(ConfigError, match="data parallel"):
        grow_with_devices(make_config("fast", num_seeds=2, shard="members"), 2)
    with pytest.raises(ConfigError, match="integer >= 1"):
        grow_with_devices(base, 0)


def test_decay_preset_is_fast_with_both_regularisers_decayed_over_a_third_of_training():
    decay, fast = make_config("decay"), make_config("fast")
    assert decay == dataclasses.replace(fast, bc_decay_epochs=20, action_l2_decay=True)
    learner = Learner(decay)
    per_epoch = decay.iterations_per_epoch * decay.updates_per_iteration
    assert float(learner.bc_coef(jnp.int32(10 * per_epoch))) == pytest.approx(0.5e-3, rel=1e-5)  # half-way
    assert float(learner.action_l2(jnp.int32(10 * per_epoch))) == pytest.approx(0.5, rel=1e-5)
    assert (
        float(learner.bc_coef(jnp.int32(30 * per_epoch))) == 0.0 == float(learner.action_l2(jnp.int32(30 * per_epoch)))
    )


def test_set_overrides_parse_as_literals():
    from regrasp_mjx.core.config_text import parse_overrides

    got = parse_overrides(["env.horizon=80", "distill.hidden=(256, 256)", "critics = 1", "name=abc"])
    assert got == {"env.horizon": 80, "distill.hidden": (256, 256), "critics": 1, "name": "abc"}
    cfg = make_config("smoke", **parse_overrides(["distill.hidden=(32,32)", "actor_ema=0"]))
    assert cfg.distill.hidden == (32, 32) and cfg.actor_ema == 0
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        parse_overrides(["horizon"])


def test_checkpoints_from_before_the_new_learner_fields_still_compare_equal():
    from regrasp_mjx.agents.ddpg_bc.checkpoint import ADDED_FIELDS, config_json, with_added_defaults

    now = config_json(make_config("smoke"))
    old = {k: v for k, v in now.items() if k not in ADDED_FIELDS}  # as written before those fields
    assert with_added_defaults(old) == now
    # a checkpoint that saved another value keeps it (and so is refused when it differs)
    assert with_added_defaults({**old, "bc_decay_epochs": 100})["bc_decay_epochs"] == 100


def test_train_config_errors():
    with pytest.raises(ConfigError, match="preset='huge' is not accepted"):
        make_config("huge")
    with pytest.raises(ConfigError, match="gamma=1.5 is not accepted"):
        make_config("smoke", gamma=1.5)
    with pytest.raises(ConfigError, match="TrainConfig has no field 'lr'"):
        make_config("smoke", lr=1e-3)
    with pytest.raises(ConfigError, match="random_eps=2 is not accepted"):
        Exploration(random_eps=2)
    assert make_config("smoke", **{"env.horizon": 50}).env.horizon == 50


@pytest.mark.parametrize(
    "build, message",
    [
        (lambda: make_config("smoke", polyak=True), "polyak=True is not accepted: a number in [0.0, 1.0]"),
        (lambda: make_config("smoke", epochs=2.0), "epochs=2.0 is not accepted: an integer >= 1"),
        (lambda: make_config("smoke", critic_layer_norm=1), "critic_layer_norm=1 is not accepted: True or False"),
        (lambda: make_config("smoke", lr_actor=float("inf")), "lr_actor=inf is not accepted: a finite number > 0"),
        (lambda: DistillConfig(lookahead=0), "distill.lookahead=0 is not accepted: an integer >= 1"),
        (lambda: DistillConfig(buffer_size=8), "distill.buffer_size=8 is not accepted: at least one batch"),
        (lambda: PlannerConfig(simplify_s=-1.0), "simplify_s=-1.0 is not accepted: a finite number >= 0"),
        (lambda: NeedleNoise(sigma_mm=11.0), "sigma_mm=11.0 is not accepted: a noise level in [0, 10] mm"),
        (lambda: PlannerPool(1, queue_size=0), "queue_size=0 is not accepted: an integer >= 1"),
    ],
)
def test_every_config_says_what_was_wrong_in_one_form(build, message):
    """One error type and one sentence shape for every config: FIELD=VALUE is not accepted: WHAT IS."""
    with pytest.raises(ConfigError) as err:
        build()
    assert str(err.value) == message


# ---- a tiny problem: wide jaws, straight-line demonstrations ---------------------------------------
EASY = EnvConfig(scene=SceneConfig(jaw_angle_deg=60.0), check_actions=False, horizon=40)


@pytest.fixture(scope="module")
def easy_env():
    return RegraspEnv(EASY)


@pytest.fixture(scope="module")
def easy_demos(easy_env):
    problems = make_testset(64, 11, EASY)
    paths = [
        np.stack(
            [np.r_[problems.start_pos[i], problems.start_quat[i]], np.r_[problems.goal_pos[i], problems.goal_quat[i]]]
        )
        for i in range(64)
    ]
    ok, rows = replay_paths(easy_env, make_replay(easy_env), problems, paths, batch=64)
    assert ok.sum() >= 48  # the straight line reaches most goals with 60 degree jaws
    episodes = [{**r, "problem_index": i, "plan_time_s": 0.0} for i, r in enumerate(rows) if ok[i]]
    demos = {k: np.concatenate([e[k] for e in episodes]) for k in ("obs", "action", "reward", "next_obs", "done")}
    return episodes, {
        **{k: jnp.asarray(v) for k, v in demos.items() if k != "done"},
        "terminal": jnp.asarray(demos["done"]),
    }


def _tiny_config(**kw) -> TrainConfig:
    base = TrainConfig(
        env=EASY,
        exploration=EXPLORATION["ddpg_bc"],
        num_envs=32,
        updates_per_iteration=50,
        iterations_per_epoch=5,
        epochs=2,
        batch_size=128,
        demo_fraction=0.5,
        buffer_size=50_000,
        hidden=(64, 64),
        lr_actor=1e-3,
        lr_critic=1e-3,
        bc_coef=1e-2,
        num_demos=48,
        **PAPER_LEARNER,  # the paper's learner; our additions are tested on their own below
    )
    return dataclasses.replace(base, **kw)


def test_target_networks_move_every_40_updates_by_polyak(easy_env, easy_demos):
    learner = Learner(_tiny_config(), easy_env)
    ts = learner.init(easy_demos[1])
    ts = learner.add_online(ts, jnp.int32(0), {k: v[:512] for k, v in easy_demos[1].items()})
    ts = jax.tree.map(lambda x: x[0], ts)  # the one seed
    update = jax.jit(learner.update)
    leaf = lambda t: np.asarray(jax.tree_util.tree_leaves(t)[0])  # noqa: E731
    first_target = leaf(ts.target_actor)
    for k in range(1, 41):
        before = leaf(ts.target_actor)
        ts, _ = update(ts, jax.random.PRNGKey(k))
        if k < 40:
            np.testing.assert_array_equal(leaf(ts.target_actor), first_target)
    np.testing.assert_allclose(leaf(ts.target_actor), 0.95 * before + 0.05 * leaf(ts.actor), atol=1e-6)
    assert int(ts.updates) == 40


def test_a_tiny_problem_is_learned_without_retracing(easy_env, easy_demos):
    cfg = _tiny_config()
    learner = Learner(cfg, easy_env)
    ts = learner.init(easy_demos[1])
    val = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), make_testset(48, 99, EASY))
    before = float(np.mean(learner.evaluate(ts.actor, ts.normalizer, val)[0].success))
    best = 0.0
    for it in range(40):
        ts, metrics, _, _ = learner.iteration(ts, jnp.float32(EXPLORATION["ddpg_bc"].at(it)[0]))
        if it % 10 == 9:
            best = max(best, float(np.mean(learner.evaluate(ts.actor, ts.normalizer, val)[0].success)))
    assert learner.trace_count == 1, "the iteration program was traced more than once"
    assert before < 0.3 and best >= 0.6, (before, best)  # seen: 0.0 -> 0.73
    assert np.isfinite(float(metrics["critic_loss"][0]))


@pytest.mark.slow
def test_seeds_axis_runs_independent_learners(easy_env, easy_demos):
    """Seed s + 1 of a two-seed program is the one-seed run with seed s + 1."""
    cfg = _tiny_config()  # the programs of the tiny problem's test (one seed) and of the resume test (two)
    pair = Learner(dataclasses.replace(cfg, seed=3, num_seeds=2), easy_env)
    alone = Learner(dataclasses.replace(cfg, seed=4), easy_env)
    ts_pair, ts_alone = pair.init(easy_demos[1]), alone.init(easy_demos[1])
    for _ in range(2):
        ts_pair, m_pair, _, _ = pair.iteration(ts_pair, jnp.float32(0.3))
        ts_alone, m_alone, _, _ = alone.iteration(ts_alone, jnp.float32(0.3))
    assert not np.allclose(m_pair["critic_loss"][0], m_pair["critic_loss"][1])  # the seeds differ
    np.testing.assert_allclose(m_pair["critic_loss"][1], m_alone["critic_loss"][0], rtol=1e-4)
    # The batched (two-seed) and the single program round differently (XLA's CPU dot kernels), and
    # Adam's first steps turn near-zero gradients' rounding into lr-sized moves: so the same seed
    # must agree a hundred times closer than the other seed does, not bit for bit.
    for a, b in zip(jax.tree_util.tree_leaves(ts_pair.actor), jax.tree_util.tree_leaves(ts_alone.actor)):
        same = np.abs(np.asarray(a[1]) - np.asarray(b[0])).max()
        other = np.abs(np.asarray(a[0]) - np.asarray(b[0])).max()
        assert same < 1e-3 * max(1.0, float(np.abs(np.asarray(b[0])).max())) and same < 0.01 * other, (same, other)


def test_actor_ema_and_cosine_learning_rate(easy_env, easy_demos):
    cfg = _tiny_config(actor_ema=0.5, lr_decay_to=0.1, target_noise=0.2)
    learner = Learner(cfg, easy_env)
    ts = learner.add_online(learner.init(easy_demos[1]), jnp.int32(0), {k: v[:512] for k, v in easy_demos[1].items()})
    ts = jax.tree.map(lambda x: x[0], ts)  # the one seed
    before = jax.tree_util.tree_leaves(ts.actor)
    ts1, _ = jax.jit(learner.update)(ts, jax.random.PRNGKey(0))
    # the moving average starts at the initial actor and moves half way to the updated one
    for e0, e1, a1 in zip(before, jax.tree_util.tree_leaves(ts1.ema_actor), jax.tree_util.tree_leaves(ts1.actor)):
        np.testing.assert_allclose(np.asarray(e1), 0.5 * np.asarray(e0) + 0.5 * np.asarray(a1), atol=1e-7)
    assert learner.policy_params(ts1) is ts1.ema_actor  # evaluated and exported
    lr = learner._learning_rate(1e-3)
    total = cfg.total_updates
    assert float(lr(0)) == pytest.approx(1e-3) and float(lr(total)) == pytest.approx(1e-4)
    assert float(lr(total // 2)) == pytest.approx(0.55e-3, rel=1e-3)
    with pytest.raises(ValueError, match="needs a key"):
        learner.learn(ts, {k: v[:64] for k, v in easy_demos[1].items()})
    # BC decay: a cosine from bc_coef to bc_coef * bc_decay_to over bc_decay_epochs epochs, then
    # flat; the action penalty follows it only with action_l2_decay; both constant by default
    big = jnp.int32(10**6)
    assert float(learner.bc_coef(big)) == pytest.approx(cfg.bc_coef)
    assert float(learner.action_l2(big)) == pytest.approx(cfg.action_l2)
    span = 2 * cfg.iterations_per_epoch * cfg.updates_per_iteration
    at = (0, span // 2, span, 3 * span)
    decay = Learner(dataclasses.replace(cfg, bc_decay_epochs=2, bc_coef=0.01), easy_env)
    assert [float(decay.bc_coef(jnp.int32(u))) for u in at] == pytest.approx([0.01, 0.005, 0.0, 0.0], abs=1e-9)
    assert float(decay.action_l2(big)) == pytest.approx(cfg.action_l2)
    floor = Learner(
        dataclasses.replace(cfg, bc_decay_epochs=2, bc_coef=0.01, bc_decay_to=0.2, action_l2=2.0, action_l2_decay=True),
        easy_env,
    )
    # cosine to 0.2: halfway is (1 + 0.2) / 2 = 0.6 of the start
    assert [float(floor.bc_coef(jnp.int32(u))) for u in at] == pytest.approx([0.01, 0.006, 0.002, 0.002], abs=1e-9)
    assert [float(floor.action_l2(jnp.int32(u))) for u in at] == pytest.approx([2.0, 1.2, 0.4, 0.4], abs=1e-6)
    # ... and the gradient step uses it: past the span of a decay to 0, the primary term is -Q alone
    gone = Learner(dataclasses.replace(cfg, bc_decay_epochs=1, action_l2=5.0, action_l2_decay=True), easy_env)
    late, batch = ts.replace(updates=jnp.int32(10**6)), {k: v[:64] for k, v in easy_demos[1].items()}
    _, m = jax.jit(gone.learn)(late, batch, jax.random.PRNGKey(1))
    assert float(m["primary_loss"]) == pytest.approx(-cfg.prm_coef * float(m["q_pi"]), rel=1e-5)
    _, m = jax.jit(learner.learn)(late, batch, jax.random.PRNGKey(1))  # constant penalty: more than -Q
    assert float(m["primary_loss"]) > -cfg.prm_coef * float(m["q_pi"]) + 1e-9


@pytest.mark.slow
def test_settings_train_side_by_side_with_paired_seeds(easy_env, easy_demos):
    cfg = make_config("smoke", "mixed,ddpg_bc", num_seeds=2)
    assert cfg.num_members == 4
    assert [cfg.member_setting(m)[0] for m in range(4)] == ["mixed", "mixed", "ddpg_bc", "ddpg_bc"]
    assert [cfg.member_seed(m) for m in range(4)] == [0, 1, 0, 1]
    assert cfg.member_setting(0)[1].targeted_eps > 0 and cfg.member_setting(2)[1].targeted_eps == 0
    with pytest.raises(ConfigError, match="each setting once"):
        make_config("smoke", "mixed,mixed")
    # Two settings, one seed: the members start alike and differ only through their own E_R.
    tiny = _tiny_config(
        updates_per_iteration=5, settings=(("a", EXPLORATION["ddpg_bc"]), ("b", EXPLORATION["ddpg_bc"]))
    )
    learner = Learner(tiny, easy_env)
    ts = learner.init(easy_demos[1])
    _, same, _, _ = learner.iteration(ts, jnp.array([0.3, 0.3]))
    np.testing.assert_array_equal(np.asarray(same["critic_loss"][0]), np.asarray(same["critic_loss"][1]))
    ts = learner.init(easy_demos[1])
    _, differ, _, _ = learner.iteration(ts, jnp.array([1.0, 0.0]))
    assert float(differ["rollout_reward"][0]) != float(differ["rollout_reward"][1])


# ---- a run killed and resumed is the run uninterrupted -------------------------------------------
@pytest.mark.slow
def test_resume_continues_exactly(tmp_path, easy_demos):
    from regrasp_mjx.workflows.trainer import Run

    save_demos(tmp_path / "demos" / "demos.npz", easy_demos[0], {"settings": {"env": dataclasses.asdict(EASY)}})
    testset = tmp_path / "test.npz"
    from regrasp_mjx.world.sampling import save_testset

    save_testset(testset, make_testset(16, 3, EASY), {"seed": 3})
    cfg = _tiny_config(iterations_per_epoch=2, validation_size=16, num_seeds=2)

    def run(out, epochs, resume=False):
        return Run(dataclasses.replace(cfg, epochs=epochs), out, tmp_path / "demos", testset, quiet=True).train(
            resume=resume
        )

    run(tmp_path / "straight", 2)
    run(tmp_path / "split", 1)
    with open(tmp_path / "split" / "log.jsonl", "a") as f:  # a row written after the checkpoint
        f.write(json.dumps({"epoch": 2, "seed": 0, "critic_loss": -1.0}) + "\n")
    run(tmp_path / "split", 2, resume=True)
    a = np.load(tmp_path / "straight" / "checkpoint" / "state.npz")
    b = np.load(tmp_path / "split" / "checkpoint" / "state.npz")
    assert a.files == b.files
    for k in a.files:
        if k == checkpoint.META:  # the state's own metadata: the same but for each run's id
            meta_a, meta_b = json.loads(str(a[k])), json.loads(str(b[k]))
            assert meta_a.pop("run_id") != meta_b.pop("run_id") and meta_a == meta_b
            assert meta_b == {
                k: v
                for k, v in json.loads((tmp_path / "split" / "checkpoint" / "meta.json").read_text()).items()
                if k != "run_id"
            }
            continue
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    log_a = [json.loads(x) for x in (tmp_path / "straight" / "log.jsonl").read_text().splitlines()]
    log_b = [json.loads(x) for x in (tmp_path / "split" / "log.jsonl").read_text().splitlines()]
    assert [r["critic_loss"] for r in log_a] == [r["critic_loss"] for r in log_b]
    assert [r["seed"] for r in log_a] == [0, 1] * 2
    final = json.loads((tmp_path / "split" / "final_eval.json").read_text())
    assert [m["seed"] for m in final["seeds"]] == [0, 1]
    for seed in (0, 1):
        for name in ("policy", "policy_last"):
            assert load_policy(tmp_path / "split" / f"seed{seed}" / name).contract["training"]["seed"] == seed
    best = max(final["seeds"], key=lambda m: m["best_validation_success"])
    assert (tmp_path / "split" / "policy" / "policy.npz").read_bytes() == (
        tmp_path / "split" / f"seed{best['seed']}" / "policy" / "policy.npz"
    ).read_bytes()
    # A checkpoint from other settings is refused, and the refused resume writes nothing into the run
    with pytest.raises(ConfigError, match="other settings"):
        checkpoint.load(tmp_path / "split" / "checkpoint", None, dataclasses.replace(cfg, epochs=2, batch_size=64))
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "split").rglob("*")}
    with pytest.raises(ConfigError, match="other settings"):
        Run(
            dataclasses.replace(cfg, epochs=2, batch_size=64), tmp_path / "split", tmp_path / "demos", testset, True
        ).train(resume=True)
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "split").rglob("*")} == before


# ---- exported policies ----------------------------------------------------------------------------
def test_exported_policy_reloads_with_identical_actions(tmp_path, easy_env, easy_demos):
    learner = Learner(_tiny_config(seed=1), easy_env)
    ts = jax.tree.map(lambda x: x[0], learner.init(easy_demos[1]))
    save_policy(tmp_path, ts.actor, ts.normalizer, (64, 64), EASY)
    policy = load_policy(tmp_path)
    obs = np.asarray(jax.random.normal(jax.random.PRNGKey(2), (100, 21)))
    expected = np.asarray(learner.nets.policy(ts.actor, ts.normalizer, jnp.asarray(obs)))
    np.testing.assert_array_equal(policy.act(obs), expected)
    assert policy.contract["action"]["max_dp_mm"] == 0.5
    with pytest.raises(ValueError, match="observation has NaN"):
        policy.act(np.full(21, np.nan))
    with pytest.raises(ValueError, match=r"accepted: \(\.\.\., 21\)"):
        policy.act(np.zeros(20))


def test_bad_policy_files(tmp_path, easy_env, easy_demos):
    with pytest.raises(PolicyError, match="policy file not found"):
        load_policy(tmp_path)
    learner = Learner(_tiny_config(seed=1), easy_env)
    ts = jax.tree.map(lambda x: x[0], learner.init(easy_demos[1]))
    save_policy(tmp_path, ts.actor, ts.normalizer, (64, 64), EASY)
    contract = json.loads((tmp_path / "policy.json").read_text())
    (tmp_path / "policy.json").write_text(json.dumps({**contract, "version": 99}))
    with pytest.raises(PolicyError, match="version 99"):
        load_policy(tmp_path)
    (tmp_path / "policy.json").write_text(
        json.dumps({**contract, "network": {**contract["network"], "hidden": [32, 32]}})
    )
    with pytest.raises(PolicyError, match=r"needs \(1, 21, 32\)"):
        load_policy(tmp_path)
    (tmp_path / "policy.json").write_text(json.dumps(contract))
    (tmp_path / "policy.npz").write_bytes(b"garbage")
    with pytest.raises(PolicyError, match="not a readable"):
        load_policy(tmp_path)


@pytest.mark.slow
def test_observation_noise_randomises_only_what_the_policy_sees_of_the_needle(easy_env, easy_demos):
    """With obs_noise_mm the stored observations carry a noisy needle and the true end-effector;
    off, they are the environment's own."""
    for noise, differs in ((0.0, False), (1.0, True)):
        learner = Learner(_tiny_config(obs_noise_mm=noise, obs_bias_mm=noise), easy_env)
        ts = jax.tree.map(lambda x: x[0], learner.init(easy_demos[1]))
        first = jax.vmap(easy_env.reset)(jax.random.split(jax.random.PRNGKey(3), 32))
        _, transitions, _ = jax.jit(learner._rollout)(ts, first, jax.random.PRNGKey(4), jnp.float32(0.0))
        seen, true = np.asarray(transitions["obs"][0]), np.asarray(first.obs)
        np.testing.assert_allclose(seen[:, 7:14], true[:, 7:14], atol=1e-6)  # the end-effector pose is known
        moved = np.linalg.norm(seen[:, :3] - true[:, :3], axis=1)
        assert (moved.min() > 1e-7) if differs else (moved.max() == 0.0)
        if differs:
            assert moved.max() < 6e-3  # at most a 1 mm bias plus a few sigma of 1 mm


@pytest.mark.slow
def test_tool_noise_makes_the_policy_see_its_tool_through_the_camera(easy_env, easy_demos):
    """With obs_tool_noise_mm the stored observations' end-effector (in the seen grasping tool's
    frame) is the camera's, within a few sigma of the truth; the needle too (seen from that frame)."""
    learner = Learner(_tiny_config(obs_tool_noise_mm=0.5), easy_env)
    ts = jax.tree.map(lambda x: x[0], learner.init(easy_demos[1]))
    first = jax.vmap(easy_env.reset)(jax.random.split(jax.random.PRNGKey(3), 32))
    _, transitions, _ = jax.jit(learner._rollout)(ts, first, jax.random.PRNGKey(4), jnp.float32(0.0))
    seen, true = np.asarray(transitions["obs"][0]), np.asarray(first.obs)
    for cols in (slice(7, 10), slice(0, 3)):  # the regrasping tool's and the needle's positions in e_g
        moved = np.linalg.norm(seen[:, cols] - true[:, cols], axis=1)
        assert moved.min() > 1e-7 and moved.max() < 6e-3
