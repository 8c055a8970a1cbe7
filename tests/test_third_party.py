"""experiments/third_party.py with our demonstrations (issue 71): a tiny demonstration set exported as a
Minari dataset, read back, cloned into an SB3 TD3 policy, fine-tuned a few steps with the
demonstrations in its replay buffer, and judged by the script's loop on a few problems. Skipped, with
the reason, where the sb3 or minari extra is not installed (torch, Stable-Baselines3, Minari)."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import sys

import numpy as np
import pytest

from regrasp_mjx.core.config import TASKS, EnvConfig, SceneConfig
from regrasp_mjx.interfaces import minari_export
from regrasp_mjx.world.sampling import save_testset
from regrasp_mjx.world.testsets import make_testset
from tests.conftest import ROOT

MISSING = [m for m in ("torch", "stable_baselines3") if importlib.util.find_spec(m) is None]
MISSING += minari_export.missing_packages()
needs_extras = pytest.mark.skipif(
    bool(MISSING),
    reason=f"{', '.join(MISSING)} not installed: the sb3 and minari extras, pip install -e '.[sb3,minari]'",
)
DATASET = "regrasp_mjx/tiny-third-party-v0"


@pytest.fixture(scope="module")
def third_party():
    spec = importlib.util.spec_from_file_location("third_party", ROOT / "experiments" / "third_party.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["third_party"] = module  # its dataclass looks its module up there
    spec.loader.exec_module(module)
    yield module
    sys.modules.pop("third_party", None)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """tests/test_minari.py's tiny paper-task set (60-degree jaws, horizon 40) exported under ``DATASET``."""
    from regrasp_mjx import export_minari
    from tests.test_minari import tiny_demos

    root = tmp_path_factory.mktemp("minari")
    demos = tiny_demos(tmp_path_factory.mktemp("demos"), "paper")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MINARI_DATASETS_PATH", str(root))
        with contextlib.redirect_stdout(io.StringIO()):
            assert export_minari.main(["--demos", str(demos.parent), "--name", DATASET, "--quiet"]) == 0
    return root


@needs_extras
def test_demonstrations_load_and_behaviour_cloning_fits_them(third_party, dataset, monkeypatch):
    import gymnasium
    import stable_baselines3 as sb3
    import torch

    torch.set_num_threads(1)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(dataset))
    demos = third_party.load_demonstrations(DATASET)
    assert demos.episodes == 6 and demos.env_name == "NeedleRegrasp"
    assert demos.config_overrides == {"env.scene.jaw_angle_deg": 60.0, "env.horizon": 40}
    assert demos.actions.shape == (len(demos), 6) and demos.obs["observation"].shape == (len(demos), 21)
    assert demos.terminations.sum() == 6 and np.all(demos.rewards[demos.terminations] == 1.0)
    env = gymnasium.make("regrasp_mjx/NeedleRegrasp-v0", config_overrides=demos.config_overrides)
    model = sb3.TD3("MultiInputPolicy", env, seed=0, learning_starts=0)

    def mse() -> float:
        with torch.no_grad():
            obs = {k: torch.as_tensor(v) for k, v in demos.obs.items()}
            return float(
                ((model.policy._predict(obs, deterministic=True) - torch.as_tensor(demos.actions)) ** 2).mean()
            )

    before = mse()
    losses = third_party.behaviour_clone(model, demos, steps=200, batch=32, lr=1e-3, seed=0)
    assert len(losses) == 10 and mse() < 0.2 * before
    for a, b in zip(model.actor.parameters(), model.actor_target.parameters()):
        assert torch.equal(a, b)  # the target starts at the cloned actor
    third_party.fill_replay_buffer(model, demos)
    assert model.replay_buffer.size() == len(demos)
    np.testing.assert_array_equal(model.replay_buffer.actions[: len(demos), 0], demos.actions)
    actor = [p.detach().clone() for p in model.actor.parameters()]
    critic = [p.detach().clone() for p in model.critic.parameters()]
    third_party.warm_critic(model, steps=4, batch=16)
    assert all(torch.equal(a, p) for a, p in zip(actor, model.actor.parameters()))  # the actor stays
    assert not all(torch.equal(c, p) for c, p in zip(critic, model.critic.parameters()))
    assert all(g["lr"] > 0 for g in model.actor.optimizer.param_groups)  # its learning rate given back


@needs_extras
@pytest.mark.slow  # 90-140 s on the 2-core VM, most of it compiling the env's programs
def test_the_script_clones_fine_tunes_and_judges(third_party, dataset, tmp_path, monkeypatch, capsys):
    """The command end to end on the tiny set: BC, a few environment steps, judged on 4 problems of the
    set's own environment; the table and JSON written, each row a verdict for every problem. Then
    TD3+BC's path with its options (its rows, file name, validation curve and offline history)."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(dataset))
    config = EnvConfig(scene=SceneConfig(jaw_angle_deg=60.0), task=TASKS["paper"], horizon=40)
    testset = tmp_path / "tiny4.npz"
    save_testset(testset, make_testset(4, 11, config), {"seed": 11, "n": 4})
    argv = ["--demos", DATASET, "--algo", "td3", "--bc-steps", "50", "--bc-batch", "32", "--critic-warmup", "4"]
    argv += ["--steps", "30", "--validation", "4", "--threads", "1", "--testset", str(testset), "--out", str(tmp_path)]
    monkeypatch.setattr(sys, "argv", ["third_party.py"])
    third_party.main(argv)
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    data = json.loads((tmp_path / "tiny-third-party-v0_td3_bc50_steps30_seed0.json").read_text())
    assert (tmp_path / "tiny-third-party-v0_td3_bc50_steps30_seed0.md").is_file()
    assert data["demonstrations"] == {
        "dataset": DATASET,
        "episodes": 6,
        "transitions": data["demonstrations"]["transitions"],
    }
    assert list(data["rows"]) == [
        "SB3 TD3 actor, BC on the demonstrations",
        "SB3 TD3, BC then 30 env steps with the demonstrations",
        "regrasp_mjx default (shipped)",
    ]
    for name, row in data["rows"].items():
        assert row["test"]["problems"] == 4 and row["validation"]["problems"] == 4
        for judged in row.values():
            assert judged["success"] + judged["collision"] + judged["time_out"] == pytest.approx(1.0)
        assert printed[name] == row["test"]["success"]

    # TD3+BC inside SB3 (the recorded result's path): normalised inputs, its own net, offline steps,
    # two environments, a validation curve
    argv = ["--demos", DATASET, "--algo", "td3", "--bc-steps", "20", "--bc-batch", "32", "--critic-warmup", "2"]
    argv += ["--obs-norm", "--net-arch", "16,16", "--bc-alpha", "2.5", "--lr", "3e-4", "--offline-steps", "4"]
    argv += ["--steps", "40", "--n-envs", "2", "--eval-every", "20", "--validation", "4", "--threads", "1"]
    third_party.main([*argv, "--testset", str(testset), "--out", str(tmp_path)])
    capsys.readouterr()
    stem = "tiny-third-party-v0_td3_bc20_steps40_norm_net16x16_lr0.0003_td3bc2.5_off4_df0.25_envs2_seed0"
    data = json.loads((tmp_path / f"{stem}.json").read_text())
    assert list(data["rows"]) == [
        "SB3 TD3 actor, BC on the demonstrations",
        "SB3 TD3+BC, BC then 4 TD3+BC steps on the demonstrations",
        "SB3 TD3+BC, BC, 4 TD3+BC steps then 40 env steps with the demonstrations",
        "regrasp_mjx default (shipped)",
    ]
    assert [c["env_steps"] for c in data["validation_curve"]] == [20, 40]
    assert [h["step"] for h in data["offline_history"]] == [4] and data["args"]["net_arch"] == [16, 16]


def test_the_script_refuses_steps_0_without_demonstrations(third_party, capsys):
    """Refused before any extra is imported: runs without them."""
    with pytest.raises(SystemExit):
        third_party.main(["--steps", "0"])
    assert "--steps must be >= 1" in capsys.readouterr().err


@needs_extras
def test_td3_bc_updates_inside_sb3_with_normalised_inputs(third_party, dataset, monkeypatch):
    """TD3+BC (``--bc-alpha``) as a subclass of SB3's TD3: its demonstrations in a buffer of their own,
    its batches all demonstrations while SB3's buffer is empty and ``demo_fraction`` of them after; its
    actor update moves the actor and reports the BC term and lambda = alpha / mean|Q|. The
    normalised extractor (``--obs-norm``) maps the demonstrations to mean 0 and std 1 (clipped)."""
    import gymnasium
    import stable_baselines3 as sb3
    import torch

    torch.set_num_threads(1)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(dataset))
    demos = third_party.load_demonstrations(DATASET)
    env = gymnasium.make("regrasp_mjx/NeedleRegrasp-v0", config_overrides=demos.config_overrides)
    extractor = third_party.normalised_extractor(torch, sb3)
    policy_kwargs = {
        "net_arch": [32, 32],
        "features_extractor_class": extractor,
        "features_extractor_kwargs": {"statistics": third_party.demonstration_statistics(demos)},
    }
    model = third_party.td3_bc_class(torch, sb3)("MultiInputPolicy", env, seed=0, policy_kwargs=policy_kwargs)
    model.bc_alpha, model.demo_fraction = 2.5, 0.5
    features = model.actor.features_extractor({k: torch.as_tensor(v) for k, v in demos.obs.items()})
    varying = np.concatenate([v.std(0) > 1e-3 for v in demos.obs.values()])  # the observation space's key order
    assert torch.allclose(features.mean(0)[varying], torch.zeros(int(varying.sum())), atol=1e-3)
    assert features.abs().max() <= 5.0  # clipped (the near-constant components' float noise included)
    assert torch.allclose(features.std(0, unbiased=False)[varying], torch.ones(int(varying.sum())), atol=1e-2)

    third_party.fill_demo_buffer(model, demos)
    assert model.demo_buffer.size() == len(demos) and model.replay_buffer.size() == 0
    assert model.sample_batch(16)[1] == 16  # the offline phase: the demonstrations alone
    actor = [p.detach().clone() for p in model.actor.parameters()]
    history = third_party.train_offline(model, steps=6, batch=16, chunk=3, log=lambda _: None)
    assert [h["step"] for h in history] == [3, 6] and history[-1]["bc_loss"] >= 0
    assert history[-1]["lambda"] > 0 and np.isfinite(history[-1]["q"])
    assert not all(torch.equal(a, p) for a, p in zip(actor, model.actor.parameters()))
    obs, _ = env.reset(seed=0)
    for _ in range(3):  # online transitions in SB3's own buffer
        action = env.action_space.sample()
        nxt, reward, terminated, _, _ = env.step(action)
        model.replay_buffer.add(
            {k: v[None] for k, v in obs.items()},
            {k: v[None] for k, v in nxt.items()},
            action[None],
            np.array([reward]),
            np.array([terminated]),
            [{}],
        )
        obs = nxt
    batch, n_demo = model.sample_batch(16)
    assert n_demo == 8 and batch.actions.shape == (16, 6) and batch.observations["observation"].shape == (16, 21)


def test_the_script_refuses_td3_bc_options_it_cannot_honour(third_party, capsys):
    """TD3+BC's options need the demonstrations (and TD3): refused before any extra is imported."""
    for argv, message in (
        (["--bc-alpha", "2.5", "--algo", "td3"], "need --demos"),
        (["--demos", "x/y-v0", "--bc-alpha", "2.5", "--algo", "sac"], "--algo td3"),
        (["--demos", "x/y-v0", "--algo", "td3", "--offline-steps", "10"], "give --bc-alpha"),
        (["--demos", "x/y-v0", "--algo", "td3", "--bc-alpha", "1", "--demo-fraction", "1"], "--demo-fraction in"),
        (["--demos", "x/y-v0", "--net-arch", "64,x"], "hidden layer sizes"),
        (["--demos", "x/y-v0", "--algo", "td3", "--no-bc-term"], "give --bc-alpha"),
        (["--demos", "x/y-v0", "--algo", "td3", "--steps", "10", "--n-envs", "2"], "needs --bc-alpha"),
    ):
        with pytest.raises(SystemExit):
            third_party.main(argv)
        assert message in capsys.readouterr().err, argv
