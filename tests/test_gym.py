"""The field's interfaces (issue 49): Playground-style ``registry.load`` and the gymnasium ids. Every
registered environment is deterministic under a key and judges as :class:`RegraspEnv` does on the
same actions; the gymnasium ids of three kinds of observation pass ``check_env``; HER's
``compute_reward`` is the step's own reward; the vector env's autoreset modes do what gymnasium 1.x
says they do, and its device arrays (issue 71) are its numpy arrays step by step."""

from __future__ import annotations

import functools
import warnings

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.base import State as BraxState
from gymnasium.utils.env_checker import check_env

import regrasp_mjx
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.interfaces import gym_envs, gym_programs, registry
from regrasp_mjx.robot import robot_errors
from regrasp_mjx.world.sampling import load_testset

ACTIONS = np.random.default_rng(0).uniform(-1.0, 1.0, (6, 6)).astype(np.float32)


def _leaves_equal(a, b) -> bool:
    return all(bool(jnp.array_equal(x, y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_the_gymnasium_ids_are_the_registry():
    assert tuple(registry.ENVS) == regrasp_mjx.GYM_NAMES
    for name in registry.ENVS:
        spec = gymnasium.spec(gym_envs.gym_id(name))
        assert spec.kwargs == {"name": name} and spec.vector_entry_point is not None


@pytest.mark.parametrize(
    "name",
    [
        "NeedleRegrasp",
        *(pytest.param(n, marks=pytest.mark.slow) for n in ("NeedleRegraspGeneral", "NeedleRegraspNoisy")),
    ],
)
def test_a_registered_env_is_deterministic_and_judges_as_regrasp_env(name):
    """Same key, same states; the reward, success, collision and time-out are RegraspEnv's on the
    same actions (the noisy variant sees the needle elsewhere, but its tool moves as commanded)."""
    env = registry.load(name, config_overrides={"env.horizon": 4})
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    inner = env.env
    key = jax.random.PRNGKey(5)
    state, again = reset(key), reset(key)
    assert _leaves_equal(state, again)
    assert not _leaves_equal(state.data, reset(jax.random.PRNGKey(6)).data)
    ref = inner.reset(jax.random.split(key)[0])
    assert _leaves_equal(state.data, ref.pipeline_state)
    assert env.observation_size == inner.observation_size == state.obs.shape[0]
    inner_step = jax.jit(inner.step)
    for a in ACTIONS[:4]:
        state, ref = step(state, a), inner_step(ref, a)
        # two compiled programs: the same poses to float32 rounding, the same verdicts exactly
        for x, y in zip(jax.tree.leaves(state.data), jax.tree.leaves(ref.pipeline_state)):
            np.testing.assert_allclose(x, y, rtol=0, atol=1e-6)
        for k in ("success", "collision", "time_out"):
            assert float(state.metrics[k]) == float(ref.metrics[k])
        assert float(state.reward) == float(ref.reward) and float(state.done) == float(ref.done)
        if name == "NeedleRegraspNoisy":
            assert not np.allclose(state.obs, ref.obs, atol=1e-6)  # it sees through its noise
        else:
            np.testing.assert_allclose(state.obs, ref.obs, rtol=0, atol=1e-5)
    assert float(state.info["truncation"]) == 1.0  # the horizon of 4, overridden


@pytest.mark.parametrize(
    "name", [pytest.param("NeedleRegraspCalibration", marks=pytest.mark.slow), "NeedleRegraspCamera"]
)
def test_a_robot_error_env_moves_the_tool_as_its_arm_would(name):
    """Without errors it is RegraspEnv; with them, the step is the commanded motion turned by the
    view's orientation error (the same length, as ``robot_errors.executed`` says), judged by RegraspEnv."""
    key = jax.random.PRNGKey(1)
    zero = {f"errors.{k}": 0.0 for k in registry.ERROR_SIZES}
    plain = registry.load(name, config_overrides=zero)
    s, ref = plain.reset(key), plain.env.reset(jax.random.split(key)[0])
    s, ref = plain.step(s, ACTIONS[0]), plain.env.step(ref, ACTIONS[0])
    assert bool(jnp.array_equal(s.obs, ref.obs)) and _leaves_equal(s.data, ref.pipeline_state)

    env = registry.load(name, config_overrides={"errors.randomise": False})
    s = env.reset(key)
    seen_needle, seen_ee = env.view_of(s.data, s.info)
    ee = np.r_[s.data.ee_pos, s.data.ee_quat]
    assert np.linalg.norm(seen_ee[:3] - ee[:3]) > 1e-5  # the tool is seen off its true pose
    turned = robot_errors.executed(None, ee[None], seen_ee[None], ACTIONS[1][None], env.env.max_dp, env.env.max_drot)[0]
    assert np.linalg.norm(turned[:3]) == pytest.approx(np.linalg.norm(np.clip(ACTIONS[1][:3], -1, 1)), rel=1e-5)
    moved = env.step(s, ACTIONS[1])
    brax_state = BraxState(s.data, s.obs, s.reward, s.done, s.metrics, s.info)
    expected = env.env.move(brax_state, turned[:3] * env.env.max_dp, turned[3:] * env.env.max_drot)
    np.testing.assert_allclose(moved.data.ee_pos, expected.pipeline_state.ee_pos, atol=1e-9)
    assert float(moved.reward) == float(expected.reward)
    assert float(moved.metrics["collision"]) == float(expected.metrics["collision"])


def test_registry_refuses_what_it_does_not_know():
    with pytest.raises(ValueError, match="no environment 'Nope'; registered: NeedleRegrasp"):
        registry.load("Nope")
    with pytest.raises(ConfigError, match="no config key 'env.horizont'; accepted: .*env.horizon"):
        registry.load("NeedleRegrasp", config_overrides={"env.horizont": 5})
    with pytest.raises(ConfigError, match="errors.view = 'eyes' is not accepted: one of exact, kinematic, camera"):
        registry.load("NeedleRegrasp", config_overrides={"errors.view": "eyes"})
    with pytest.raises(ConfigError, match=r"errors.needle_sigma_mm = -1.0 is not accepted: a number in \[0, 10\]"):
        registry.load("NeedleRegrasp", config_overrides={"errors.needle_sigma_mm": -1.0})
    with pytest.raises(ConfigError, match="horizon"):
        registry.load("NeedleRegrasp", config_overrides={"env.horizon": 0})
    cfg = registry.default_config("NeedleRegraspNoisy")
    assert cfg.errors.needle_sigma_mm == 0.5 and cfg.env.horizon == 100


# the paper's task, the general one (another observation) and the camera's view (the needle and
# both tools seen with error: the error views' code path); NeedleRegraspNoisy and
# NeedleRegraspCalibration differ from these in error sizes and which tool is seen, not in spaces
@pytest.mark.parametrize(
    "name",
    [
        "NeedleRegrasp",
        *(pytest.param(n, marks=pytest.mark.slow) for n in ("NeedleRegraspGeneral", "NeedleRegraspCamera")),
    ],
)
def test_check_env_passes(name):
    env = gymnasium.make(gym_envs.gym_id(name), config_overrides={"env.horizon": 3})
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*Box observation space (minimum|maximum) value")
        check_env(env.unwrapped, skip_render_check=True)
    obs, _ = env.reset(seed=2)
    assert env.observation_space.contains(obs)
    again, _ = env.reset(seed=2)
    assert all(np.array_equal(obs[k], again[k]) for k in obs)


def test_her_reward_is_the_step_reward_through_a_successful_episode():
    """The shipped default drives paper300's first problem to success through the gymnasium env;
    ``compute_reward`` from the goals (and the info) is every step's reward, +1 at the end."""
    policy = regrasp_mjx.load_policy()
    env = gymnasium.make("regrasp_mjx/NeedleRegrasp-v0")
    episodes, _ = load_testset("paper300")
    obs, info = env.reset(seed=0, options={"episode": episodes.row(slice(0, 1))})
    rewards, computed = [], []
    for _ in range(100):
        obs, reward, terminated, truncated, info = env.step(policy.act(obs["observation"]))
        rewards.append(reward)
        computed.append(float(env.unwrapped.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)))
        if terminated or truncated:
            break
    assert info["is_success"] and rewards[-1] == 1.0
    assert computed == pytest.approx(rewards)
    # vectorised over a batch of goals, a collision read from a sequence of info dicts (as SB3's HER passes them)
    a = np.stack([obs["achieved_goal"]] * 3)
    got = env.unwrapped.compute_reward(a, a, np.array([{"collision": False}, {"collision": True}, {}]))
    np.testing.assert_array_equal(got, [1.0, -1.0, 1.0])
    far = a.copy()
    far[:, 0] += 1.5  # mm: beyond the 1 mm tolerance
    np.testing.assert_array_equal(env.unwrapped.compute_reward(far, a, None), np.float32([-0.02] * 3))


def test_bad_actions_are_refused():
    env = gymnasium.make("regrasp_mjx/NeedleRegrasp-v0")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action has shape \(5,\); accepted: \(6,\)"):
        env.step(np.zeros(5))
    with pytest.raises(ValueError, match="action has NaN or inf; accepted: finite numbers"):
        env.step(np.array([np.nan, 0, 0, 0, 0, 0]))
    venv = gym_envs.NeedleRegraspVectorEnv(num_envs=2)
    with pytest.raises(RuntimeError, match="reset"):
        venv.step(np.zeros((2, 6)))
    with pytest.raises(ValueError, match="autoreset_mode 'later' is not accepted"):
        gym_envs.NeedleRegraspVectorEnv(num_envs=2, autoreset_mode="later")


def _run(venv, steps: int, seed: int):
    out = [venv.reset(seed=seed)]
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        out.append(venv.step(rng.uniform(-1, 1, (venv.num_envs, 6)).astype(np.float32)))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["same_step", "next_step"])
def test_the_vector_env_autoresets_as_gymnasium_says(mode):
    venv = gymnasium.make_vec(
        "regrasp_mjx/NeedleRegrasp-v0",
        num_envs=3,
        vectorization_mode="vector_entry_point",
        autoreset_mode=mode,
        config_overrides={"env.horizon": 2},
    )
    assert venv.metadata["autoreset_mode"] == gym_envs.AUTORESET[mode]
    run = _run(venv, 5, seed=4)
    again = _run(venv, 5, seed=4)
    for a, b in zip(run, again):  # the same seed, the same numbers
        assert all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))
    # every episode ends by step 2 (horizon 2 or sooner)
    obs1, _, term1, trunc1, info1 = run[1]
    obs2, reward2, term2, trunc2, info2 = run[2]
    ended = term2 | trunc2 | term1 | trunc1
    assert ended.all()
    if mode == "same_step":
        end2 = term2 | trunc2
        assert np.array_equal(info2["_final_obs"], end2)
        # the returned observation of an ended lane is a new episode's first; the last is in final_obs
        rows = np.flatnonzero(end2)
        assert rows.size and not np.allclose(obs2["observation"][rows], info2["final_obs"]["observation"][rows])
    else:
        first_end = term1 | trunc1
        # a lane that ended at step 1 starts over at step 2: no reward, not terminated
        assert np.all(reward2[first_end] == 0.0) and not np.any(term2[first_end] | trunc2[first_end])


def test_the_vector_env_starts_from_given_problems():
    episodes, _ = load_testset("paper300")
    venv = gym_envs.NeedleRegraspVectorEnv(num_envs=2, autoreset_mode="disabled")
    obs, _ = venv.reset(seed=0, options={"episodes": episodes.row(slice(0, 2))})
    single = gymnasium.make("regrasp_mjx/NeedleRegrasp-v0")
    first, _ = single.reset(seed=9, options={"episode": episodes.row(slice(1, 2))})
    np.testing.assert_allclose(obs["observation"][1], first["observation"], atol=1e-6)
    with pytest.raises(ValueError, match=r"options\['episodes'\] has rows \[3\]; accepted: an Episode of 2 rows"):
        venv.reset(options={"episodes": episodes.row(slice(0, 3))})


def test_rgb_array_renders_the_scene():
    from regrasp_mjx.workflows import render

    env = gymnasium.make("regrasp_mjx/NeedleRegrasp-v0", render_mode="rgb_array", width=64, height=48)
    env.reset(seed=0)
    try:
        frame = env.render()
    except render.RenderUnavailable as err:
        pytest.skip(f"no OpenGL on this machine ({err})")
    finally:
        env.close()
    assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8 and frame.std() > 0


@pytest.mark.slow
def test_ended_episodes_restart_from_new_problems_the_pool_redrawn_when_used_up():
    """Horizon 1: every lane ends every step, so two lanes use up the pool (two problems a lane)
    every other step; twelve restarts are twelve different problems."""
    venv = gym_envs.NeedleRegraspVectorEnv(num_envs=2, config_overrides={"env.horizon": 1})
    obs, _ = venv.reset(seed=1)
    seen = [obs["desired_goal"]]
    for _ in range(6):
        obs, _, terminated, truncated, info = venv.step(np.zeros((2, 6), np.float32))
        assert np.all(terminated | truncated) and info["_final_obs"].all()
        seen.append(obs["desired_goal"])
    starts = np.concatenate(seen)
    assert len(np.unique(np.round(starts, 6), axis=0)) == len(starts) == 14


def _compare(a, b, path: str = "") -> None:
    """The same structure (keys in order), array kinds, dtypes, shapes and values; ``b`` holds jax arrays."""
    if isinstance(a, (dict, tuple)):
        assert type(a) is type(b) and len(a) == len(b), path
        keys = list(a) if isinstance(a, dict) else range(len(a))
        assert keys == (list(b) if isinstance(b, dict) else range(len(b))), path
        for k in keys:
            _compare(a[k], b[k], f"{path}/{k}")
        return
    assert isinstance(a, np.ndarray) and isinstance(b, jax.Array), path
    assert a.dtype == b.dtype and a.shape == b.shape, (path, a.dtype, b.dtype, a.shape, b.shape)
    if a.dtype == np.bool_:
        np.testing.assert_array_equal(a, b, err_msg=path)
    else:  # two compiled programs (one packs its outputs): equal bit for bit here, compared to float32 rounding
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6, err_msg=path)


@functools.cache
def _pair(mode: str) -> dict:
    """The vector env with numpy and with jax arrays (3 lanes, horizon 2), made once for the tests below."""
    return {
        arrays: gym_envs.NeedleRegraspVectorEnv(
            num_envs=3, autoreset_mode=mode, config_overrides={"env.horizon": 2}, arrays=arrays
        )
        for arrays in ("numpy", "jax")
    }


START = {"episodes": load_testset("paper300")[0].row(slice(0, 3))}


@pytest.mark.parametrize(
    "mode", ["same_step", *(pytest.param(m, marks=pytest.mark.slow) for m in ("next_step", "disabled"))]
)
def test_device_arrays_equal_the_numpy_path_step_by_step(mode):
    """``arrays="jax"`` returns what the numpy path returns (names, dtypes, shapes, values, infos and
    final observations), as jax arrays, from device actions; through ends, restarts and a redraw of
    the pool (3 lanes of horizon 2 restart at least 9 times in 11 steps; it holds 2 problems a lane)."""
    host, device = _pair(mode)["numpy"], _pair(mode)["jax"]
    _compare(host.reset(seed=3, options=START), device.reset(seed=3, options=START))
    rng, ended = np.random.default_rng(3), 0
    for _ in range(11):
        actions = rng.uniform(-1, 1, (3, 6)).astype(np.float32)
        a, b = host.step(actions), device.step(jnp.asarray(actions))
        _compare(a, b)
        ended += int(np.sum(a[2] | a[3]))
        # the numpy path's per-environment arrays are the caller's to change, as they were
        assert all(x.flags.writeable for x in (a[1], a[2], a[3], a[4]["success"], a[4]["distance_mm"]))
    # restarts (each lane's last end may be yet to restart) used up the pool: it was redrawn
    assert ended - 3 > gym_programs.Program.POOL_PER_ENV * 3 if mode != "disabled" else ended > 0


def test_device_arrays_refuse_bad_actions_and_start_again():
    with pytest.raises(ValueError, match="arrays='torch' is not accepted: one of numpy, jax"):
        gym_envs.NeedleRegraspVectorEnv(num_envs=2, arrays="torch")
    venv = _pair("same_step")["jax"]
    venv.reset(seed=0, options=START)
    with pytest.raises(ValueError, match=r"action has shape \(3, 5\); accepted: \(3, 6\)"):
        venv.step(jnp.zeros((3, 5)))
    with pytest.raises(ValueError, match="action has dtype bool"):
        venv.step(jnp.zeros((3, 6), bool))
    obs, *_ = venv.step(np.zeros((3, 6), np.float32))  # numpy actions are taken too
    assert isinstance(obs["observation"], jax.Array)
    with pytest.raises(Exception, match="action has NaN or inf"):  # refused inside the compiled step
        jax.block_until_ready(venv.step(jnp.zeros((3, 6)).at[1, 2].set(jnp.nan)))
    with pytest.raises(RuntimeError, match="call reset"):  # its state was given to the failed step
        venv.step(jnp.zeros((3, 6)))
    venv.reset(seed=1, options=START)
    _, reward, *_ = venv.step(jnp.zeros((3, 6)))
    assert isinstance(reward, jax.Array) and reward.shape == (3,)


def test_the_packed_forms_round_trip():
    """The pool's rows (every 32-bit dtype and booleans) and the numpy path's one buffer (typed views:
    vectors read-only as np.asarray of a jax array is, one number per environment a writable copy)."""
    tree = {
        "f": jnp.arange(12, dtype=jnp.float32).reshape(3, 2, 2) / 7,
        "i": jnp.asarray([-1, 0, 5], jnp.int32),
        "u": jnp.asarray([[1, 2], [3, 4], [2**32 - 1, 0]], jnp.uint32),
        "b": jnp.asarray([True, False, True]),
    }
    rows = gym_programs.Rows(jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape[1:], x.dtype), tree))
    packed = rows.encode(tree)
    assert packed.shape == (3, 4 + 1 + 2 + 1) and packed.dtype == jnp.uint32
    assert _leaves_equal(rows.decode(packed), tree) and rows.decode(packed)["b"].dtype == jnp.bool_
    with pytest.raises(TypeError, match="dtype float16 cannot be a pool row"):
        gym_programs.Rows({"h": jax.ShapeDtypeStruct((2,), jnp.float16)})

    fields = {"flag": tree["b"], "reward": jnp.asarray([0.5, -1.0, 2.0]), "obs": tree["f"].reshape(3, 4)}
    layout = gym_programs.Layout(fields)
    assert [name for name, *_ in layout.fields] == ["obs", "reward", "flag"]  # 32-bit vectors, numbers, flags
    read = layout.read(jax.jit(layout.pack)(fields))
    for k, v in fields.items():
        assert read[k].dtype == v.dtype and np.array_equal(read[k], v)
    assert read["reward"].flags.writeable and read["flag"].flags.writeable and not read["obs"].flags.writeable
