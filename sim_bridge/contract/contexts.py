"""The paper's context-randomized DMC tasks: parameter lists, number of prototypes, and what
every node needs to know of a task without simulating it (actuator names, camera, which bodies a
context scales).

Values are copied verbatim from ProtoCAD (ICLR 2023), appendix Table ``env_para``
("The environmental settings") and Table ``setting_k`` (K per task). A context is a dict
``{param: scale}`` with one value per parameter of the task: ``m`` scales masses and ``d``
joint damping, both relative to the model's defaults (see ``sim_bridge.sim.envs`` for which bodies
and joints). Each parameter is drawn independently from its list, i.e. uniformly over the
cartesian grid of the split. Pure data: no dm_control or ROS import here.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from types import MappingProxyType
from typing import Mapping

import numpy as np

from sim_bridge.contract.topics import SPLITS

Values = Mapping[str, tuple[float, ...]]


@dataclass(frozen=True, eq=False)
class TaskSpec:
    """One task: its dm_control (domain, task), context parameters and their split lists."""

    name: str
    domain: str
    task: str
    params: tuple[str, ...]
    train: Values
    test: Values
    num_prototypes: int

    def values(self, split: str) -> Values:
        """The per-parameter value lists of a split ('train' or 'test')."""
        check_split(split)
        return self.train if split == "train" else self.test

    def contexts(self, split: str) -> list[dict[str, float]]:
        """Every context of a split: the cartesian product of its per-parameter lists."""
        values = self.values(split)
        grid = itertools.product(*(values[p] for p in self.params))
        return [dict(zip(self.params, combo)) for combo in grid]

    def stratified(self, split: str, k: int) -> list[dict[str, float]]:
        """A fixed subset of k contexts of the split, stratified: every value of each parameter
        appears equally often (as far as k allows). One parameter: k values evenly spaced over
        its list. Two (m, d): m cycles through its list while d steps through its own by a
        stride coprime with its length, shifted on each pass (an 8 x 8 grid, k = 8: (0, 0),
        (1, 3), (2, 6), (3, 1), ... in index terms, so m and d are not correlated); k >= the
        grid's size gives the whole grid. What periodic evaluations use."""
        allc = self.contexts(split)
        if k <= 0 or k >= len(allc):
            return allc
        values = self.values(split)
        if len(self.params) == 1:
            (p,) = self.params
            idx = np.unique(np.round(np.linspace(0, len(values[p]) - 1, k)).astype(int))
            return [{p: values[p][i]} for i in idx]
        if len(self.params) != 2:
            raise NotImplementedError("stratified subsets of more than two context parameters")
        pa, pb = self.params
        na, nb = len(values[pa]), len(values[pb])
        stride = next(s for s in range(max(1, round(0.38 * nb)), nb + 1) if math.gcd(s, nb) == 1)
        passes = -(-k // na)
        shift = max(1, nb // passes)
        out = []
        for j in range(k):
            i, r = j % na, j // na
            out.append({pa: values[pa][i], pb: values[pb][(i * stride + r * shift) % nb]})
        return out

    def sample(self, split: str, rng: np.random.Generator) -> dict[str, float]:
        """A context drawn uniformly from the split's grid (each parameter independently)."""
        values = self.values(split)
        return {p: values[p][int(rng.integers(len(values[p])))] for p in self.params}

    def validate(self, context: Mapping[str, float], split: str) -> dict[str, float]:
        """``context`` as the table's exact values, or ValueError saying what is allowed."""
        values = self.values(split)
        if not isinstance(context, Mapping) or set(context) != set(self.params):
            got = sorted(context) if isinstance(context, Mapping) else type(context).__name__
            raise ValueError(f"{self.name}: a context needs exactly the parameters "
                             f"{list(self.params)}, got {got}")
        out = {}
        for p in self.params:
            try:
                v = float(context[p])
            except (TypeError, ValueError):
                raise ValueError(f"{self.name}: context value {p}={context[p]!r} is not a number")
            # Tolerance only absorbs float round-trips (e.g. through a float32 message); the
            # table's own value is returned so masses are always default * table value.
            match = [a for a in values[p] if math.isclose(v, a, rel_tol=0.0, abs_tol=1e-6)]
            if not match:
                other = "test" if split == "train" else "train"
                hint = (f" ({p}={v:g} belongs to the {other} split)"
                        if any(math.isclose(v, a, abs_tol=1e-6)
                               for a in self.values(other)[p]) else "")
                raise ValueError(f"{self.name}: {p}={v:g} is not in the {split} split{hint}; "
                                 f"allowed {p} values for {split}: {list(values[p])}")
            out[p] = match[0]
        return out


def check_split(split: str) -> str:
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; valid splits: {list(SPLITS)}")
    return split


def _spec(name: str, train: dict[str, tuple[float, ...]], test: dict[str, tuple[float, ...]],
          k: int) -> TaskSpec:
    domain, task = name.split("_", 1)
    return TaskSpec(name, domain, task, tuple(train), MappingProxyType(train),
                    MappingProxyType(test), k)


# Cheetah and Walker share one row of the table (m and d), as do Finger and Hopper (m).
_LINK_TRAIN = (0.75, 0.85, 1.00, 1.15, 1.25)
_LINK_TEST = (0.2, 0.3, 0.4, 0.5, 1.5, 1.6, 1.7, 1.8)
_MASS_TRAIN = (0.5, 0.75, 1.0, 1.25, 1.5)
_MASS_TEST = (0.25, 0.375, 1.75, 2.0)
_MD_TRAIN = {"m": _LINK_TRAIN, "d": _LINK_TRAIN}
_MD_TEST = {"m": _LINK_TEST, "d": _LINK_TEST}

TASKS: dict[str, TaskSpec] = {s.name: s for s in (
    _spec("cheetah_run", _MD_TRAIN, _MD_TEST, 100),
    _spec("finger_spin", {"m": _MASS_TRAIN}, {"m": _MASS_TEST}, 100),
    _spec("hopper_hop", {"m": _MASS_TRAIN}, {"m": _MASS_TEST}, 50),
    _spec("hopper_stand", {"m": _MASS_TRAIN}, {"m": _MASS_TEST}, 100),
    _spec("pendulum_swingup",
          {"m": (0.75, 0.8, 0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.15, 1.2, 1.25)},
          {"m": (0.2, 0.4, 0.5, 0.7, 1.3, 1.5, 1.6, 1.8)}, 100),
    _spec("quadruped_run", {"m": (0.85, 0.90, 0.95, 1.00)},
          {"m": (0.20, 0.25, 0.30, 0.35, 0.40, 0.45, 0.50, 0.55, 0.60)}, 100),
    _spec("walker_run", _MD_TRAIN, _MD_TEST, 50),
    _spec("walker_walk", _MD_TRAIN, _MD_TEST, 100),
)}


# Actuator names of each domain's dm_control model, in action order (read once from the suite's
# XML files; tests/sim_bridge/sim/test_envs.py checks them against the models), so that nodes and trainers that
# never simulate (a robot's policy node, a GPU learner) know the action layout without mujoco.
ACTUATORS: dict[str, tuple[str, ...]] = {
    "cheetah": ("bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot"),
    "finger": ("proximal", "distal"),
    "hopper": ("waist", "hip", "knee", "ankle"),
    "pendulum": ("torque",),
    "quadruped": tuple(f"{j}_{leg}" for leg in ("front_left", "front_right", "back_right", "back_left")
                       for j in ("yaw", "lift", "extend")),
    "walker": tuple(f"{side}_{j}" for side in ("right", "left") for j in ("hip", "knee", "ankle")),
}


#: The camera each domain is rendered from: Dreamer/DreamerPro DMC (quadruped 2, the rest 0).
CAMERA_IDS = {"quadruped": 2}


@dataclass(frozen=True)
class BodyScaling:
    """Which part of a domain's model a context scales: the bodies in the subtree of ``root``
    (without ``root`` itself when ``include_root`` is False), and their joints' damping. Bodies
    in the subtrees of ``inverse`` get 1/m instead of m (CaDM's and RIA's Ant)."""

    root: str
    include_root: bool = True
    damping: bool = False
    inverse: tuple[str, ...] = ()


#: What a context scales in each domain's model (sim_bridge.sim.envs applies it; its docstring says why).
SCALING = {
    "cheetah": BodyScaling("torso", damping=True),
    "walker": BodyScaling("torso", damping=True),
    "hopper": BodyScaling("torso"),
    "finger": BodyScaling("proximal"),  # the finger, not the spinner (see module docstring)
    "pendulum": BodyScaling("pole"),
    # Legs only, as the Ant of CaDM and RIA, whose mass ranges the paper's quadruped copies
    # (train 0.85-1.0, test 0.2-0.6): the front legs by m, the back legs by 1/m
    # (younggyoseo/CaDM cadm/envs/ant_env.py: mass[2:8] *= m, mass[8:14] *= 1/m; RIA's
    # ria/envs/ant_env.py is the same). At m = 0.2 the back legs weigh 5x, the front 0.2x.
    "quadruped": BodyScaling("torso", include_root=False,
                             inverse=("hip_back_right", "hip_back_left")),
}


def task_actuators(task: str) -> list[str]:
    """The action names of a task, in order (ValueError for an unknown task)."""
    return list(ACTUATORS[get_task(task).domain])


def get_task(name: str) -> TaskSpec:
    """The TaskSpec of ``name`` (e.g. 'cheetah_run'), or ValueError listing the valid names."""
    try:
        return TASKS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown task {name!r}; valid tasks: {sorted(TASKS)}") from None


def normalized_log_context(values: np.ndarray, task: str) -> np.ndarray:
    """Scale factors (..., P) in the order of `task`'s params -> (log v - mu) / sigma, with mu
    and sigma of log v over the task's training grid: the true context as a model reads it
    (unseen contexts land outside [-1.5, 1.5] where the training grid spans it)."""
    spec = get_task(task)
    grid = np.log(np.array([[c[p] for p in spec.params] for c in spec.contexts("train")], np.float64))
    mu, sigma = grid.mean(0), grid.std(0)
    return (np.log(np.asarray(values, np.float64)) - mu) / np.where(sigma > 0, sigma, 1.0)


def context_label(context: Mapping[str, float], split: str | None = None) -> str:
    """'m=0.75 d=1' (or 'train m=0.75 d=1' with the split): how a context is named in tables,
    logs and plots."""
    body = " ".join(f"{k}={float(v):g}" for k, v in context.items())
    return f"{split} {body}" if split else body
