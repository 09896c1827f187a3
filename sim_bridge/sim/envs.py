"""Context-randomized DeepMind Control tasks with 64x64 pixel observations (ProtoCAD setting).

Each reset picks a context (see ``sim_bridge.contract.contexts``) and scales the model relative to the
defaults captured once at construction, so contexts never compound across episodes:

- cheetah, walker: ``m`` scales every link of the agent (all bodies but the world) and ``d``
  the damping of every agent joint (the root slide/hinge joints have zero damping, so in
  effect the actuated joints);
- hopper: ``m`` scales every body of the hopper (torso, pelvis, thigh, calf, foot);
- finger: ``m`` scales the finger (proximal and distal links) but NOT the spinner: the paper
  scales "the mass of the finger agent", and the spinner is the object the agent acts on,
  whose inertia is what the task's reward is about;
- pendulum: ``m`` scales the pole;
- quadruped: ``m`` scales the bodies of the front legs (hip, knee, ankle, toe) and ``1/m`` those
  of the back legs, not the torso: the Ant of CaDM and RIA, whose mass ranges the paper copies
  (``sim_bridge.contract.contexts.SCALING`` quotes the source).

Only ``body_mass`` (and ``dof_damping``) are scaled, not ``body_inertia``: that is what the
environments of this line of work do (CaDM's ``change_env`` sets ``model.body_mass`` and
``model.dof_damping`` from scaled copies, younggyoseo/CaDM cadm/envs/half_cheetah_env.py; RIA, whose
settings the paper follows, builds on them), and MuJoCo keeps the two independent: a run-time
``body_mass`` edit leaves the compiled ``body_inertia`` as it was (``mj_setConst`` does not
recompute inertia from geoms). ``scale_inertia=True`` scales the inertia by the same factor
instead (a uniform density change of the same geometry), this project's behaviour before
2026-12-01 and the physics behind the committed CPU results. After editing the model,
``mj_setConst`` recomputes the derived constants (subtree masses, dof_M0 and invweight0 used by
constraint regularisation, actuator_acc0, trackcom camera offsets), exactly as if the scaled
model had been compiled.

Actions are in [-1, 1]^A for every task and mapped affinely onto the task's actuator range
(DreamerV2/DreamerPro ``NormalizeAction``; only quadruped's range differs from [-1, 1]);
finite values outside [-1, 1] are clipped. Images come from camera 0 (quadruped: camera 2)
as in Dreamer/DreamerPro, rendered once per agent step (never the intermediate repeats).

dm_control is imported lazily: with MUJOCO_GL=egl importing it opens an EGL display, which
must neither happen in processes that never render (the VectorEnv parent) nor before a fork.
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Mapping, Sequence

import numpy as np

from sim_bridge.contract.contexts import CAMERA_IDS, SCALING, TaskSpec, check_split, get_task

if TYPE_CHECKING:
    from dm_control.mujoco import Physics

RenderQuality = Literal["default", "fast"]
RENDER_QUALITIES = ("default", "fast")
@dataclass
class Observation:
    """One agent step. reward is summed over the action repeats that led here (0 on is_first);
    context/split/episode/step are ground truth for evaluation only, never for the agent."""

    image: np.ndarray  # (H, W, 3) uint8
    reward: float
    discount: float
    is_first: bool
    is_last: bool
    is_terminal: bool
    context: dict[str, float]
    split: str
    episode: int
    step: int


def check_env_args(task: str, split: str = "train", seed: Any = 0, **kwargs: Any
                   ) -> tuple[TaskSpec, dict[str, float] | None]:
    """Validate ContextDMCEnv's arguments without building it (no dm_control import).

    Returns (spec, canonical fixed context or None); raises TypeError/ValueError.
    """
    inspect.signature(ContextDMCEnv).bind(task, split, seed, **kwargs)  # TypeError on typos
    opts = {name: p.default for name, p in inspect.signature(ContextDMCEnv).parameters.items()
            if p.default is not inspect.Parameter.empty}
    opts.update(kwargs)
    spec = get_task(task)
    check_split(split)
    for name in ("action_repeat", "image_size", "time_limit"):
        value = opts[name]
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    camera = opts["camera_size"]
    if camera is not None and not (len(camera) == 2 and all(
            isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1 for v in camera)):
        raise ValueError(f"camera_size must be (height, width) in pixels, got {camera!r}")
    if opts["render_quality"] not in RENDER_QUALITIES:
        raise ValueError(f"unknown render_quality {opts['render_quality']!r}; "
                         f"valid: {list(RENDER_QUALITIES)}")
    context = opts["context"]
    return spec, None if context is None else spec.validate(context, split)


class ContextDMCEnv:
    """A paper task with a context drawn from ``split`` at every reset (or fixed by ``context``).

    ``seed`` (an int or an ``np.random.SeedSequence``) seeds both the context draws and
    dm_control's own initial-state randomness, so it reproduces contexts and frames.
    ``time_limit`` counts env steps (physics control steps): 1000 = 500 agent steps at
    action_repeat 2. ``render_quality='fast'`` renders without shadows, reflections and MSAA
    into a framebuffer of the image size (10-15x faster with Mesa's llvmpipe; the pixels
    differ by a mean of 1-14 of 255, see scripts/bench_envs.py); 'default' keeps the suite's
    look, pixel-identical to dm_control's ``physics.render`` as used by Dreamer/DreamerPro.
    ``first_episode`` (an episode number) seeds each episode on its own instead: episode k's
    context draw and initial state come from (seed, k) alone, so two runs with one seed see
    the same episodes whatever they did before, and a resumed run (built again with the number
    of its next episode) sees the episodes an uninterrupted one would have.
    ``camera_size`` (height, width) renders every frame at that size instead of the square
    image_size, through the same camera: MuJoCo's field of view is vertical, so the centered
    square of a wider frame shows what the square render shows (a real camera's frame, for the
    sim bridge's camera option; the model's input is then `sim_bridge.contract.camera.model_image`
    of it).
    """

    def __init__(self, task: str, split: str = "train", seed: int | np.random.SeedSequence = 0, *,
                 action_repeat: int = 2, image_size: int = 64,
                 render_quality: RenderQuality = "fast",
                 context: Mapping[str, float] | None = None, time_limit: int = 1000,
                 scale_inertia: bool = False, first_episode: int | None = None,
                 camera_size: tuple[int, int] | None = None):
        self.spec, self._fixed_context = check_env_args(
            task, split, seed, action_repeat=action_repeat, image_size=image_size,
            render_quality=render_quality, context=context, time_limit=time_limit,
            camera_size=camera_size)
        self.split, self.action_repeat, self.time_limit = split, int(action_repeat), int(time_limit)
        self.image_size, self.render_quality = int(image_size), render_quality
        self.scale_inertia = bool(scale_inertia)

        import mujoco
        from dm_control import suite
        from dm_control.mujoco.engine import Camera

        seq = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        # Children built from spawn_key, not seq.spawn(): spawn() advances the caller's
        # SeedSequence, so passing one object twice would give two different envs.
        context_seq, task_seq = (np.random.SeedSequence(seq.entropy, pool_size=seq.pool_size,
                                                        spawn_key=(*seq.spawn_key, k))
                                 for k in (0, 1))
        self._rng = np.random.default_rng(context_seq)
        self._seq, self._first_episode = seq, first_episode
        # The episode length is ours to count (in env steps); dm_control's own limit is a float
        # division of seconds by control_timestep, which we keep out of the way.
        self._env = suite.load(self.spec.domain, self.spec.task, task_kwargs={
            "random": np.random.RandomState(np.random.MT19937(task_seq)),
            "time_limit": float("inf")})
        self.physics: Physics = self._env.physics
        self._mujoco = mujoco
        model = self.physics.model

        spec = self._env.action_spec()
        self.action_dim = int(spec.shape[0])
        self.action_names = [model.id2name(i, "actuator") for i in range(model.nu)]
        self._action_center = (spec.maximum + spec.minimum) / 2.0
        self._action_half = (spec.maximum - spec.minimum) / 2.0
        self.control_dt = float(self._env.control_timestep()) * self.action_repeat

        scaling = SCALING[self.spec.domain]
        self._bodies = _subtree(model, model.name2id(scaling.root, "body"), scaling.include_root)
        self._dofs = (np.flatnonzero(np.isin(model.dof_bodyid, self._bodies))
                      if scaling.damping else np.zeros(0, dtype=int))
        assert scaling.damping == ("d" in self.spec.params), self.spec.name
        inverse = [b for r in scaling.inverse
                   for b in _subtree(model, model.name2id(r, "body"), True)]
        # m ** power per scaled body: +1, or -1 in the subtrees scaling.inverse names
        self._mass_power = np.where(np.isin(self._bodies, inverse), -1.0, 1.0)
        self._default_mass = model.body_mass[self._bodies].copy()
        self._default_inertia = model.body_inertia[self._bodies].copy()
        self._default_damping = model.dof_damping[self._dofs].copy()

        # Offscreen buffer and MSAA are fixed when the GL context is created (by the Camera).
        vis = model.vis
        height, width = (int(v) for v in camera_size) if camera_size else (self.image_size,) * 2
        if render_quality == "fast":
            vis.quality.offsamples = 0
            vis.global_.offwidth, vis.global_.offheight = width, height
        else:
            vis.global_.offwidth = max(vis.global_.offwidth, width)
            vis.global_.offheight = max(vis.global_.offheight, height)
        # One persistent camera: physics.render() would rebuild an mjvScene every frame.
        self._camera = Camera(self.physics, height=height, width=width,
                              camera_id=CAMERA_IDS.get(self.spec.domain, 0))
        if render_quality == "fast":
            flags = self._camera.scene.flags
            flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
            flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0

        self._context: dict[str, float] | None = None
        self._episode = -1
        self._step = 0
        self._env_steps = 0
        self._done = True

    @property
    def context(self) -> dict[str, float] | None:
        """The current episode's context (None before the first reset)."""
        return None if self._context is None else dict(self._context)

    def reset(self, context: Mapping[str, float] | None = None) -> Observation:
        """Start an episode with ``context`` (must be in this env's split), the fixed context,
        or a uniform draw from the split; returns the is_first observation."""
        if self._first_episode is not None:
            self._seed_episode(self._first_episode + self._episode + 1)
        if context is not None:
            context = self.spec.validate(context, self.split)
        else:
            context = self._fixed_context or self.spec.sample(self.split, self._rng)
        self._apply(context)
        # dm_control's reset (mj_resetData, the task's initialize_episode, mj_forward) runs on
        # the scaled model, so the initial state and first frame already see the context.
        self._env.reset()
        self._context = context
        self._episode += 1
        self._step = self._env_steps = 0
        self._done = False
        return self._observe(0.0, 1.0, is_first=True, is_last=False, is_terminal=False)

    def _seed_episode(self, k: int) -> None:
        """Episode k's own streams: its context draw (2, k) and dm_control's initial state (3, k)."""
        seq = self._seq
        key = lambda *extra: np.random.SeedSequence(seq.entropy, pool_size=seq.pool_size,  # noqa: E731
                                                    spawn_key=(*seq.spawn_key, *extra))
        self._rng = np.random.default_rng(key(2, k))
        self._env.task.random.seed(int(key(3, k).generate_state(1)[0]))

    def step(self, action: Sequence[float] | np.ndarray) -> Observation:
        """Apply ``action`` (shape (A,), finite, clipped to [-1, 1]) for action_repeat env steps."""
        if self._done:
            raise RuntimeError("call reset() first: no episode is running"
                               if self._context is None else
                               "the episode ended (is_last); call reset() to start the next one")
        ctrl = self._action_center + self._action_half * self._check_action(action)
        reward, discount, ended = 0.0, 1.0, False
        for _ in range(self.action_repeat):
            ts = self._env.step(ctrl)
            self._env_steps += 1
            reward += float(ts.reward or 0.0)
            discount = float(ts.discount)
            ended = ts.last()
            if ended or self._env_steps >= self.time_limit:
                break
        is_terminal = ended and discount == 0.0
        self._done = ended or self._env_steps >= self.time_limit
        self._step += 1
        return self._observe(reward, discount, is_first=False, is_last=self._done,
                             is_terminal=is_terminal)

    def render(self) -> np.ndarray:
        """The current frame, (image_size, image_size, 3) uint8, or camera_size x 3."""
        # Camera.render returns a flipped view of its reused buffer: copy it out.
        return self._camera.render().copy()

    def close(self) -> None:
        """Free the rendering resources (the env is unusable afterwards)."""
        camera, self._camera = getattr(self, "_camera", None), None
        if camera is not None:
            camera._scene.free()  # noqa: SLF001 (dm_control offers no public free)
            self.physics.free()

    def __enter__(self) -> ContextDMCEnv:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _apply(self, context: Mapping[str, float]) -> None:
        model = self.physics.model
        m, d = context["m"], context.get("d", 1.0)
        factor = np.power(m, self._mass_power)
        model.body_mass[self._bodies] = self._default_mass * factor
        model.body_inertia[self._bodies] = self._default_inertia * (
            factor[:, None] if self.scale_inertia else 1.0)
        model.dof_damping[self._dofs] = self._default_damping * d
        # mj_setConst overwrites mjData (it evaluates qpos0); the reset that follows restores it.
        self._mujoco.mj_setConst(model.ptr, self.physics.data.ptr)

    def _check_action(self, action: Sequence[float] | np.ndarray) -> np.ndarray:
        try:
            a = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise ValueError(f"action must be {self.action_dim} numbers, got {action!r}") from err
        if a.shape != (self.action_dim,):
            raise ValueError(f"action has shape {a.shape}, expected ({self.action_dim},) "
                             f"for {self.spec.name}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action contains NaN or inf: {a.tolist()}")
        return np.clip(a, -1.0, 1.0)

    def _observe(self, reward: float, discount: float, *, is_first: bool, is_last: bool,
                 is_terminal: bool) -> Observation:
        assert self._context is not None
        return Observation(self.render(), reward, discount, is_first, is_last, is_terminal,
                           dict(self._context), self.split, self._episode, self._step)


def _subtree(model: Any, root: int, include_root: bool) -> np.ndarray:
    """Ids of the bodies in the kinematic subtree of ``root`` (parents precede children)."""
    ids = [root]
    for body in range(root + 1, model.nbody):
        if model.body_parentid[body] in ids:
            ids.append(body)
    return np.array(ids[0 if include_root else 1:], dtype=int)
