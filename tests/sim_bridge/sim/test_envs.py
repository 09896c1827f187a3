"""sim_bridge.contract.contexts / sim_bridge.sim.envs against real dm_control physics and EGL rendering.

Scaling is checked by reading the physics model after reset() and comparing it with a fresh,
unmodified suite.load() of the same task: the intended bodies/joints are default * value
(bit-exact), everything else is untouched.
"""
from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from sim_bridge.contract.contexts import TASKS, get_task
from sim_bridge.sim.envs import ContextDMCEnv

# The paper's appendix Table env_para and Table setting_k, typed in again on purpose.
LINK_TRAIN = (0.75, 0.85, 1.00, 1.15, 1.25)
LINK_TEST = (0.2, 0.3, 0.4, 0.5, 1.5, 1.6, 1.7, 1.8)
MASS_TRAIN = (0.5, 0.75, 1.0, 1.25, 1.5)
MASS_TEST = (0.25, 0.375, 1.75, 2.0)
PAPER = {  # task: (train, test, K)
    "cheetah_run": ({"m": LINK_TRAIN, "d": LINK_TRAIN}, {"m": LINK_TEST, "d": LINK_TEST}, 100),
    "finger_spin": ({"m": MASS_TRAIN}, {"m": MASS_TEST}, 100),
    "hopper_hop": ({"m": MASS_TRAIN}, {"m": MASS_TEST}, 50),
    "hopper_stand": ({"m": MASS_TRAIN}, {"m": MASS_TEST}, 100),
    "pendulum_swingup": ({"m": (0.75, 0.8, 0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.15, 1.2, 1.25)},
                         {"m": (0.2, 0.4, 0.5, 0.7, 1.3, 1.5, 1.6, 1.8)}, 100),
    "quadruped_run": ({"m": (0.85, 0.90, 0.95, 1.00)},
                      {"m": (0.20, 0.25, 0.30, 0.35, 0.40, 0.45, 0.50, 0.55, 0.60)}, 100),
    "walker_run": ({"m": LINK_TRAIN, "d": LINK_TRAIN}, {"m": LINK_TEST, "d": LINK_TEST}, 50),
    "walker_walk": ({"m": LINK_TRAIN, "d": LINK_TRAIN}, {"m": LINK_TEST, "d": LINK_TEST}, 100),
}
LEGS = [f"{part}_{side}" for part in ("hip", "knee", "ankle", "toe")
        for side in ("front_left", "front_right", "back_right", "back_left")]
WALKER = ["torso"] + [f"{s}_{p}" for s in ("right", "left") for p in ("thigh", "leg", "foot")]
MASS_BODIES = {  # the bodies each domain's m must scale (world and finger's spinner excluded)
    "cheetah": ["torso", "bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot"],
    "walker": WALKER,
    "hopper": ["torso", "pelvis", "thigh", "calf", "foot"],
    "finger": ["proximal", "distal"],
    "pendulum": ["pole"],
    "quadruped": LEGS,
}
DAMPED = {"cheetah", "walker"}  # d scales every joint (dof) of these agents
# bodies scaled by 1/m instead of m: quadruped's back legs (CaDM's and RIA's Ant)
INVERSE = {"quadruped": [f"{part}_{side}" for part in ("hip", "knee", "ankle", "toe")
                         for side in ("back_right", "back_left")]}


def mass_factor(ref, domain: str, m: float) -> np.ndarray:
    """Per body of the pristine model: what its mass is multiplied by at scale m."""
    f = np.ones(ref.nbody)
    f[[ref.name2id(n, "body") for n in MASS_BODIES[domain]]] = m
    f[[ref.name2id(n, "body") for n in INVERSE.get(domain, [])]] = 1.0 / m
    return f


@pytest.fixture(scope="module")
def reference():
    """A pristine, reset dm_control model per task (finger spin edits damping in its reset)."""
    from dm_control import suite
    cache = {}

    def get(task: str):
        if task not in cache:
            spec = get_task(task)
            env = suite.load(spec.domain, spec.task)
            env.reset()
            cache[task] = env.physics.model
        return cache[task]

    return get


@pytest.fixture(scope="module")
def make_env():
    """Module-wide cache of envs keyed by their arguments (building one costs a GL context)."""
    cache: dict = {}

    def get(task: str, split: str = "train", **kw) -> ContextDMCEnv:
        key = (task, split, repr(sorted(kw.items())))
        if key not in cache:
            cache[key] = ContextDMCEnv(task, split, **kw)
        return cache[key]

    yield get
    for env in cache.values():
        env.close()


def test_tables_are_the_papers_and_splits_are_disjoint():
    assert sorted(TASKS) == sorted(PAPER)
    for name, (train, test, k) in PAPER.items():
        spec = TASKS[name]
        assert (spec.name, spec.num_prototypes, spec.params) == (name, k, tuple(train))
        assert dict(spec.train) == train and dict(spec.test) == test
        for p in spec.params:
            assert not set(spec.train[p]) & set(spec.test[p]), (name, p)
        for split, values in (("train", train), ("test", test)):
            expected = [dict(zip(values, c)) for c in itertools.product(*values.values())]
            assert spec.contexts(split) == expected


@pytest.mark.parametrize("task", sorted(PAPER))
def test_every_context_scales_exactly_the_intended_bodies_and_joints(task, make_env, reference):
    ref = reference(task)
    domain = get_task(task).domain
    body_ids = [ref.name2id(n, "body") for n in MASS_BODIES[domain]]
    mass_mask = np.isin(np.arange(ref.nbody), body_ids)
    dof_mask = np.full(ref.nv, domain in DAMPED)
    for split in ("train", "test"):
        env = make_env(task, split)
        model = env.physics.model
        for context in get_task(task).contexts(split):
            obs = env.reset(context)
            assert obs.context == context and obs.split == split and obs.is_first
            m, d = context["m"], context.get("d", 1.0)
            np.testing.assert_allclose(model.body_mass, ref.body_mass * mass_factor(ref, domain, m),
                                       rtol=1e-12)
            # CaDM/RIA: mass only, the compiled inertia stays
            np.testing.assert_array_equal(model.body_inertia, ref.body_inertia)
            np.testing.assert_array_equal(model.body_mass[~mass_mask], ref.body_mass[~mass_mask])
            np.testing.assert_array_equal(model.dof_damping[dof_mask], ref.dof_damping[dof_mask] * d)
            np.testing.assert_array_equal(model.dof_damping[~dof_mask], ref.dof_damping[~dof_mask])
            # Derived constants follow the new masses (mj_setConst ran).
            np.testing.assert_allclose(model.body_subtreemass[0], model.body_mass.sum())


@pytest.mark.parametrize("task,split", [("cheetah_run", "test"), ("quadruped_run", "train"),
                                        ("finger_spin", "test")])
def test_100_resets_stay_in_split_and_never_compound(task, split, make_env, reference):
    env, ref = make_env(task, split), reference(task)
    allowed = get_task(task).contexts(split)
    seen = []
    for _ in range(100):
        obs = env.reset()
        assert obs.context in allowed and obs.split == split
        seen.append(tuple(obs.context.values()))
    assert len(set(seen)) > len(allowed) // 2  # really sampled, not stuck on one context
    m, d = obs.context["m"], obs.context.get("d", 1.0)
    np.testing.assert_allclose(env.physics.model.body_mass,
                               ref.body_mass * mass_factor(ref, get_task(task).domain, m), rtol=1e-12)
    np.testing.assert_array_equal(env.physics.model.body_inertia, ref.body_inertia)
    if "d" in obs.context:
        np.testing.assert_array_equal(env.physics.model.dof_damping, ref.dof_damping * d)


def test_seed_reproduces_contexts_and_frames():
    runs = []
    for seed in (7, 7, 8):
        with ContextDMCEnv("walker_walk", seed=seed) as env:
            episodes = []
            for _ in range(3):
                obs = env.reset()
                after = env.step(np.full(env.action_dim, 0.3))
                episodes.append((obs.context, obs.image, after.image, obs.episode))
            runs.append(episodes)
    for (c1, f1, g1, e1), (c2, f2, g2, e2) in zip(runs[0], runs[1]):
        assert c1 == c2 and e1 == e2
        np.testing.assert_array_equal(f1, f2)
        np.testing.assert_array_equal(g1, g2)
    assert [e[3] for e in runs[0]] == [0, 1, 2]
    assert [e[0] for e in runs[0]] != [e[0] for e in runs[2]]  # another seed, other contexts
    assert not np.array_equal(runs[0][0][1], runs[2][0][1])


def test_episode_keyed_draws_do_not_depend_on_what_came_before():
    """Paired runs and resumes: episode k of a seed is the same episode whether the env was
    built at episode 0 and ran k episodes (each a different length) or built at k."""
    def episode(env, steps):
        obs = env.reset()
        for _ in range(steps):
            env.step(np.full(env.action_dim, 0.3))
        return obs.context, obs.image, env.physics.data.qpos.copy()

    with ContextDMCEnv("walker_walk", seed=7, first_episode=0) as env:
        history = [episode(env, steps) for steps in (1, 5, 2, 0)]
    with ContextDMCEnv("walker_walk", seed=7, first_episode=2) as env:
        resumed = [episode(env, 0), episode(env, 0)]
    for (c1, f1, q1), (c2, f2, q2) in zip(history[2:], resumed):
        assert c1 == c2
        np.testing.assert_array_equal(f1, f2)          # same initial state and first frame
    assert len({tuple(sorted(c.items())) for c, _, _ in history}) > 1   # episodes still differ
    with ContextDMCEnv("walker_walk", seed=8, first_episode=2) as env:
        _, other_frame, other_qpos = episode(env, 0)
    assert not np.array_equal(other_qpos, resumed[0][2])   # another seed, another episode 2


def test_step_repeats_actions_and_sums_rewards_like_dm_control(make_env):
    from dm_control import suite
    env = make_env("cheetah_run", "train")
    ref = suite.load("cheetah", "run")
    obs = env.reset({"m": 1.0, "d": 1.0})  # the default model: comparable to plain dm_control
    assert obs.reward == 0.0 and obs.discount == 1.0 and obs.step == 0
    assert obs.image.shape == (64, 64, 3) and obs.image.dtype == np.uint8
    ref.reset()
    ref.physics.set_state(env.physics.get_state())
    ref.physics.forward()
    rng = np.random.default_rng(0)
    for step in range(1, 4):
        action = rng.uniform(-1, 1, env.action_dim)
        obs = env.step(action)
        expected = sum(ref.step(action).reward for _ in range(2))
        assert obs.reward == pytest.approx(expected, rel=1e-12, abs=1e-12)
        assert obs.step == step and not (obs.is_first or obs.is_last or obs.is_terminal)
        np.testing.assert_allclose(env.physics.data.qpos, ref.physics.data.qpos, atol=1e-12)
    assert env.control_dt == pytest.approx(2 * ref.control_timestep())


def test_episode_ends_at_time_limit_in_env_steps(make_env):
    env = make_env("pendulum_swingup", "train")  # default time_limit 1000 env steps
    env.reset()
    ends = [env.step([0.0]).is_last for _ in range(500)]
    assert ends == [False] * 499 + [True]
    with pytest.raises(RuntimeError, match="reset"):
        env.step([0.0])
    short = make_env("pendulum_swingup", "train", time_limit=5)  # 2 + 2 + 1 env steps
    short.reset()
    last = [short.step([0.0]) for _ in range(3)]
    assert [o.is_last for o in last] == [False, False, True]
    assert last[-1].discount == 1.0 and not last[-1].is_terminal  # time limit, not terminal


def test_actions_are_normalized_and_clipped_to_the_spec(make_env):
    env = make_env("quadruped_run", "train")  # the one task whose range is not [-1, 1]
    low, high = env._env.action_spec().minimum, env._env.action_spec().maximum
    env.reset()
    env.step(np.ones(12))
    np.testing.assert_allclose(env.physics.data.ctrl, high)
    env.step(np.full(12, -5.0))
    np.testing.assert_allclose(env.physics.data.ctrl, low)
    env.step(np.zeros(12))
    np.testing.assert_allclose(env.physics.data.ctrl, (low + high) / 2)


def test_bad_input_is_rejected_with_clear_errors(make_env):
    with pytest.raises(ValueError, match="valid tasks: .*cheetah_run"):
        get_task("cheetah_walk")
    with pytest.raises(ValueError, match="valid tasks"):
        ContextDMCEnv("cartpole_swingup")
    with pytest.raises(ValueError, match=r"valid splits: \['train', 'test'\]"):
        ContextDMCEnv("pendulum_swingup", split="val")
    with pytest.raises(ValueError, match=r"allowed m values for train: \[0.75, 0.8"):
        ContextDMCEnv("pendulum_swingup", context={"m": 3.0})
    with pytest.raises(ValueError, match="belongs to the test split"):
        ContextDMCEnv("cheetah_run", context={"m": 0.2, "d": 1.0})
    with pytest.raises(ValueError, match=r"exactly the parameters \['m', 'd'\]"):
        ContextDMCEnv("walker_walk", context={"m": 1.0})
    with pytest.raises(ValueError, match="render_quality"):
        ContextDMCEnv("pendulum_swingup", render_quality="ultra")
    with pytest.raises(ValueError, match="action_repeat"):
        ContextDMCEnv("pendulum_swingup", action_repeat=0)
    with pytest.raises(TypeError):
        ContextDMCEnv("pendulum_swingup", renderquality="fast")

    env = make_env("hopper_hop", "test")
    with ContextDMCEnv("pendulum_swingup") as fresh, pytest.raises(RuntimeError, match="reset"):
        fresh.step([0.0])
    with pytest.raises(ValueError, match="allowed m values for test"):
        env.reset({"m": 1.0})
    obs = env.reset({"m": 0.375})
    assert obs.context == {"m": 0.375}
    for bad, what in [(np.zeros(3), "shape"), (np.zeros((1, 4)), "shape"), (0.5, "shape"),
                      ([0, np.nan, 0, 0], "NaN"), ([0, 0, np.inf, 0], "inf"),
                      (["a", "b", "c", "d"], "4 numbers")]:
        with pytest.raises(ValueError, match=what):
            env.step(bad)
    assert env.step(np.zeros(4)).step == 1  # still usable after rejected actions


def test_fixed_context_is_held_for_every_episode(make_env):
    env = make_env("hopper_stand", "test", context={"m": 1.75})
    assert [env.reset().context for _ in range(3)] == [{"m": 1.75}] * 3


def test_fast_and_default_rendering_show_the_same_state(make_env):
    fast = make_env("walker_run", "train", seed=3, render_quality="fast")
    default = make_env("walker_run", "train", seed=3, render_quality="default")
    assert fast.physics.model.vis.quality.offsamples == 0
    assert fast.physics.model.vis.global_.offwidth == 64
    assert default.physics.model.vis.quality.offsamples == 4  # the suite's own setting
    a, b = fast.reset(), default.reset()
    np.testing.assert_array_equal(fast.physics.get_state(), default.physics.get_state())
    assert a.context == b.context
    diff = np.abs(a.image.astype(int) - b.image.astype(int)).mean()
    assert 0 < diff < 20  # no shadows/reflection/MSAA: same picture, slightly different pixels


@pytest.mark.parametrize("task", sorted(TASKS))
def test_stored_actuator_names_are_the_models_in_action_order(task):
    """sim_bridge.contract.contexts.ACTUATORS is read once from the suite's XML: it must stay the model's."""
    import importlib.util

    import mujoco

    from sim_bridge.contract.contexts import task_actuators

    spec = TASKS[task]
    root = list(importlib.util.find_spec("dm_control").submodule_search_locations)[0]
    model = mujoco.MjModel.from_xml_path(str(Path(root, "suite", f"{spec.domain}.xml")))
    assert task_actuators(task) == [model.actuator(i).name for i in range(model.nu)]


def test_scale_inertia_scales_the_inertia_of_the_scaled_bodies_too(reference):
    from sim_bridge.sim.envs import ContextDMCEnv

    ref = reference("pendulum_swingup")
    mask = np.isin(np.arange(ref.nbody), [ref.name2id(n, "body") for n in MASS_BODIES["pendulum"]])
    with ContextDMCEnv("pendulum_swingup", split="test", seed=0, scale_inertia=True) as env:
        m = env.reset().context["m"]
        model = env.physics.model
        np.testing.assert_array_equal(model.body_inertia[mask], ref.body_inertia[mask] * m)
        np.testing.assert_array_equal(model.body_inertia[~mask], ref.body_inertia[~mask])
        np.testing.assert_array_equal(model.body_mass[mask], ref.body_mass[mask] * m)
