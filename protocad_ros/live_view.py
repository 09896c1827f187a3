"""Live rerun stream of the policy: image, context features u/w/e, action, reward on 'sim_time'.

Used by the policy node (one ``log_step`` per answered observation); off by default, and when
off neither this module's callers nor ``LiveView`` import ``rerun`` (no import cost, no
dependency at run time). No rclpy import here: the node maps its ROS parameters
(``PARAMETERS`` below) onto ``LiveView.from_params``.

Modes (``rerun_mode`` parameter):

========== ==================================================================================
off        nothing is logged (default)
spawn      start a local rerun viewer process and stream to it (needs a display)
connect    stream to a running viewer / server over gRPC; ``rerun_url`` defaults to
           ``rerun+http://127.0.0.1:9876/proxy`` (what a plain ``rerun`` command listens on)
save       write an .rrd file at ``rerun_path`` (open it later with ``rerun FILE.rrd``)
========== ==================================================================================

Entity paths (timeline ``sim_time``, the observation's header stamp as a duration):

============================ ====================================================================
/policy/image                rr.Image: the 64x64 observation the action answers
/policy/features/u           rr.BarChart: projection u_t (D values)
/policy/features/e           rr.BarChart: prototype-aggregated context e_t (D values)
/policy/assignment           rr.BarChart: prototype assignment w_t (K probabilities)
/policy/assignment_top       rr.Scalars: index of the most probable prototype (argmax w_t)
/policy/assignment_entropy   rr.Scalars: entropy of w_t in nats (low = one prototype fires)
/policy/action               rr.Scalars: one series per action dimension (names static)
/policy/reward               rr.Scalars: reward arriving with the observation
/policy/context/<param>      rr.Scalars: the true context, when the caller passes it
/policy/episode_start        rr.TextLog: one line at every is_first observation
============================ ====================================================================

Wiring in the policy node (its ``add_act_callback`` hook; parameters as in ``PARAMETERS``)::

    view = LiveView.from_params(rerun_mode, rerun_url, rerun_path, action_names=names)
    if view.enabled:
        node.add_act_callback(view.on_act)      # one log_step per answered observation
    ...
    view.close()                                # at shutdown: completes an .rrd file

Cost: about 1.6 ms per step (64x64 image, K=100 bars; 2-core dev machine under load).
'connect' with nothing listening blocks the constructor for about 5 s (rerun's connection
attempt), then buffers and finally drops; 'spawn' without a display (DISPLAY /
WAYLAND_DISPLAY) is a ValueError at construction. The stream carries its
own layout (``policy_blueprint``). ``open_stream`` also gives trainer/viz/rerun_log.py's
TrainingRecorder a live target, e.g. ``TrainingRecorder(open_stream('spawn'))``.
"""
from __future__ import annotations

import math
import os
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

MODES = ("off", "spawn", "connect", "save")
DEFAULT_URL = "rerun+http://127.0.0.1:9876/proxy"

# ROS parameters of the policy node for the live stream (name -> default); the node declares
# them and passes the values to LiveView.from_params(**values).
PARAMETERS: dict[str, str] = {
    "rerun_mode": "off",   # off | spawn | connect | save
    "rerun_url": "",       # connect: gRPC url of a viewer ('' = DEFAULT_URL)
    "rerun_path": "",      # save: .rrd output file (required in save mode)
}

POLICY_ROOT = "/policy"


def check_mode(mode: str) -> str:
    mode = (mode or "off").strip().lower()
    if mode not in MODES:
        raise ValueError(f"unknown rerun mode {mode!r}; valid modes: {list(MODES)}")
    return mode


def check_display() -> None:
    """ValueError unless a viewer window can open here (DISPLAY or WAYLAND_DISPLAY set):
    without one a spawned viewer dies and the stream waits on it for seconds, then drops."""
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise ValueError("rerun mode 'spawn' needs a display (DISPLAY / WAYLAND_DISPLAY unset): "
                         "use 'save' (then `rerun FILE.rrd` elsewhere) or 'connect' to a viewer")


def open_stream(mode: str, *, url: str | None = None, path: str | Path | None = None,
                application_id: str = "protocad", recording_id: str | None = None,
                blueprint: Any = None):
    """A ``rerun.RecordingStream`` sending to ``mode`` ('spawn' | 'connect' | 'save'), or None
    for 'off'. ``blueprint`` (a ``rerun.blueprint.Blueprint``) is sent as the default layout.

    Raises ValueError for an unknown mode or a save without a path; the parent directory of a
    save path is created.
    """
    mode = check_mode(mode)
    if mode == "off":
        return None
    if mode == "save" and not path:
        raise ValueError("rerun mode 'save' needs a path for the .rrd file (rerun_path / --out)")
    if mode == "spawn":
        check_display()
    import rerun as rr

    rec = rr.RecordingStream(application_id, recording_id=recording_id)
    if mode == "save":
        path = Path(path)
        if path.suffix != ".rrd":
            raise ValueError(f"rerun save path must end in .rrd, got {str(path)!r}")
        path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(str(path), default_blueprint=blueprint)
    elif mode == "spawn":
        rec.spawn(default_blueprint=blueprint)
    else:  # connect
        rec.connect_grpc(url or DEFAULT_URL, default_blueprint=blueprint)
    return rec


def _as_vector(value: Any) -> np.ndarray:
    return np.asarray(value if value is not None else (), dtype=np.float64).reshape(-1)


class LiveView:
    """Streams one policy step at a time to rerun. ``LiveView()`` (mode 'off') does nothing.

    ``log_step`` never raises because of the viewer (rerun buffers and drops on its own side);
    it raises ValueError only for malformed arguments (a programming error in the caller).
    """

    def __init__(self, mode: str = "off", url: str | None = None, path: str | Path | None = None,
                 *, action_names: Sequence[str] | None = None, application_id: str = "protocad_policy",
                 recording_id: str | None = None):
        self.mode = check_mode(mode)
        self.url, self.path = url or None, (Path(path) if path else None)
        self.action_names = list(action_names) if action_names else None
        self._rec = None
        self._names_sent = False
        self._context_keys: tuple[str, ...] = ()
        self.steps = 0
        if self.mode != "off":
            self._rec = open_stream(self.mode, url=self.url, path=self.path,
                                    application_id=application_id, recording_id=recording_id,
                                    blueprint=policy_blueprint())

    @classmethod
    def from_params(cls, rerun_mode: str = "off", rerun_url: str = "", rerun_path: str = "",
                    **kw: Any) -> "LiveView":
        """From the policy node's ROS parameters (PARAMETERS); '' means unset."""
        return cls(rerun_mode, url=rerun_url or None, path=rerun_path or None, **kw)

    @property
    def enabled(self) -> bool:
        return self._rec is not None

    @property
    def recording(self):
        """The underlying rerun.RecordingStream (None when off)."""
        return self._rec

    def log_step(self, sim_time_ns: int, image: np.ndarray | None, *, u: Any = None, w: Any = None,
                 e: Any = None, action: Any = None, reward: float | None = None,
                 is_first: bool = False, context: Mapping[str, float] | None = None) -> None:
        """Log one answered observation at ``sim_time_ns`` (the observation's header stamp).

        image (H,W,3) uint8 or None; u, e (D,), w (K,) float arrays (size 0 / None for variants
        without context features: not logged); action (A,); reward float.
        """
        if self._rec is None:
            return
        import rerun as rr

        rec = self._rec
        t = int(sim_time_ns)
        if t < 0:
            raise ValueError(f"sim_time_ns must be >= 0, got {sim_time_ns}")
        rec.set_time("sim_time", duration=np.timedelta64(t, "ns"))
        if image is not None:
            img = np.asarray(image)
            if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] not in (1, 3, 4):
                raise ValueError(f"image must be (H,W,3) uint8, got {img.dtype} {img.shape}")
            rec.log(f"{POLICY_ROOT}/image", rr.Image(img))
        for name, value in (("u", u), ("e", e)):
            vec = _as_vector(value)
            if vec.size:
                rec.log(f"{POLICY_ROOT}/features/{name}", rr.BarChart(vec.astype(np.float32)))
        wv = _as_vector(w)
        if wv.size:
            rec.log(f"{POLICY_ROOT}/assignment", rr.BarChart(wv.astype(np.float32)))
            rec.log(f"{POLICY_ROOT}/assignment_top", rr.Scalars(float(np.argmax(wv))))
            p = np.clip(wv, 1e-12, 1.0)
            rec.log(f"{POLICY_ROOT}/assignment_entropy", rr.Scalars(float(-(p * np.log(p)).sum())))
        if action is not None:
            act = _as_vector(action)
            if act.size:
                if not self._names_sent:
                    names = self.action_names or [f"a{i}" for i in range(act.size)]
                    if len(names) != act.size:
                        names = [f"a{i}" for i in range(act.size)]
                    rec.log(f"{POLICY_ROOT}/action", rr.SeriesLines(names=names), static=True)
                    self._names_sent = True
                rec.log(f"{POLICY_ROOT}/action", rr.Scalars(act))
        if reward is not None and math.isfinite(float(reward)):
            rec.log(f"{POLICY_ROOT}/reward", rr.Scalars(float(reward)))
        if context:
            for k, v in context.items():
                rec.log(f"{POLICY_ROOT}/context/{path_part(str(k))}", rr.Scalars(float(v)))
        if is_first:
            ctx = ", ".join(f"{k}={float(v):g}" for k, v in (context or {}).items())
            rec.log(f"{POLICY_ROOT}/episode_start", rr.TextLog(f"episode start {ctx}".strip()))
        self.steps += 1

    def on_act(self, event: Any) -> None:
        """Act callback for the policy node (``PolicyNode.add_act_callback(view.on_act)``):
        logs a protocad_ros.node.policy_node.ActEvent (stamp_ns, info: StepInfo, image, action,
        features: ContextFeatures u/w/e)."""
        if self._rec is None:
            return
        info, feats = event.info, event.features
        self.log_step(event.stamp_ns, event.image, u=getattr(feats, "u", None),
                      w=getattr(feats, "w", None), e=getattr(feats, "e", None), action=event.action,
                      reward=getattr(info, "reward", None), is_first=bool(getattr(info, "is_first", False)))

    def flush(self) -> None:
        if self._rec is not None:
            try:
                self._rec.flush()
            except Exception as exc:  # pragma: no cover - transport trouble must not kill a node  # noqa: BLE001
                print(f"[live_view] flush failed: {exc}", file=sys.stderr)

    def close(self) -> None:
        """Flush and disconnect (an .rrd file is complete afterwards)."""
        if self._rec is None:
            return
        rec, self._rec = self._rec, None
        try:
            rec.flush()
            rec.disconnect()
        except Exception as exc:  # pragma: no cover  # noqa: BLE001
            print(f"[live_view] close failed: {exc}", file=sys.stderr)

    def __enter__(self) -> "LiveView":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def path_part(name: str) -> str:
    """A readable entity-path part: letters, digits, '_', '-', '.'; everything else -> '_'."""
    out = "".join(c if (c.isalnum() or c in "_-.") else "_" for c in name)
    return out or "_"


def policy_blueprint():
    """Layout of the live stream: image | assignment + features | action/reward series."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(origin=f"{POLICY_ROOT}/image", name="observation"),
            rrb.Vertical(
                rrb.BarChartView(origin=f"{POLICY_ROOT}/assignment", name="prototype assignment w"),
                rrb.BarChartView(origin=f"{POLICY_ROOT}/features/u", name="u"),
                rrb.BarChartView(origin=f"{POLICY_ROOT}/features/e", name="e"),
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(origin=f"{POLICY_ROOT}/action", name="action"),
                rrb.TimeSeriesView(origin=f"{POLICY_ROOT}/reward", name="reward"),
                rrb.TimeSeriesView(
                    origin=POLICY_ROOT, name="assignment over time",
                    contents=[f"{POLICY_ROOT}/assignment_top", f"{POLICY_ROOT}/assignment_entropy",
                              f"{POLICY_ROOT}/context/**"]),
            ),
            column_shares=[2, 2, 3],
        ),
    )
