"""The layout (rerun blueprint) of a context view, over the entities of
trainer/viz/context_log.py: tabs "Contexts" (u_e and RSSM state, 3D coloured by the first
parameter and 2D by split, with prototypes and context means, plus the legend), "Features
u / e", "Assignments" and "Predictions" (observations | reconstructions, open-loop truth |
prediction, errors)."""
from __future__ import annotations

from typing import Any, Sequence

import rerun.blueprint as rrb

from trainer.viz.context_view import ContextView


def context_blueprint_parts(view: ContextView | None, method: str = "pca") -> list:
    """Tabs: 'Contexts' (u_e and RSSM state 3D + 2D), 'Features u / e', 'Assignments',
    'Predictions'."""
    method = view.method if view is not None else method
    params = view.params if view is not None else ()
    color = f"by_{params[0]}" if params else "by_split"

    def space_view(feature: str, dim: int, by: str, name: str):
        origin = f"/embeddings/{feature}/{method}{dim}d"
        contents = [f"{origin}/{by}", f"{origin}/prototypes", f"{origin}/contexts"]
        # Frame the points (they span [-1, 1]); unused prototypes may lie further out.
        if dim == 3:
            return rrb.Spatial3DView(origin=origin, contents=contents, name=name,
                                     eye_controls=rrb.EyeControls3D(position=[1.3, -1.6, 1.1],
                                                                    look_target=[0, 0, 0],
                                                                    eye_up=[0, 0, 1]))
        return rrb.Spatial2DView(origin=origin, contents=contents, name=name,
                                 visual_bounds=rrb.VisualBounds2D(x_range=[-1.15, 1.15],
                                                                  y_range=[-1.15, 1.15]))

    ctx = rrb.Horizontal(
        rrb.Vertical(space_view("u_e", 3, color, f"learned feature u,e (3D, {color})"),
                     space_view("u_e", 2, "by_split", "learned feature u,e (2D, by split)")),
        rrb.Vertical(space_view("rssm_state", 3, color, f"RSSM state (3D, {color})"),
                     space_view("rssm_state", 2, "by_split", "RSSM state (2D, by split)")),
        rrb.TextDocumentView(origin="/embeddings/legend", name="legend"),
        column_shares=[3, 3, 1], name="Contexts")
    feats = rrb.Grid(*[space_view(f, 3, b, f"{f} ({b})") for f in ("u", "e")
                       for b in (color, "by_split")], name="Features u / e")
    assign = rrb.Horizontal(
        rrb.TensorView(origin="/assignment/by_context", name="mean assignment w per episode"),
        rrb.Vertical(rrb.TensorView(origin="/episodes/0/assignment", name="episode 0: w over time"),
                     rrb.TimeSeriesView(origin="/episodes", name="top prototype per step")),
        rrb.TextDocumentView(origin="/assignment/episodes", name="episodes"),
        name="Assignments")
    preds = rrb.Horizontal(
        rrb.Vertical(rrb.Spatial2DView(origin="/reconstruction/truth", name="observations"),
                     rrb.Spatial2DView(origin="/reconstruction/model", name="reconstructions"),
                     rrb.TimeSeriesView(origin="/reconstruction/mse", name="reconstruction MSE")),
        rrb.Vertical(rrb.Spatial2DView(origin="/open_loop/truth", name="open loop: truth"),
                     rrb.Spatial2DView(origin="/open_loop/prediction", name="open loop: prediction"),
                     rrb.TimeSeriesView(origin="/open_loop/mse", name="open-loop MSE")),
        rrb.Spatial2DView(origin="/open_loop/montage", name="open loop montage"),
        name="Predictions")
    return [ctx, feats, assign, preds]


def context_blueprint(view: ContextView | None = None, extra_tabs: Sequence[Any] = ()):
    # Side panels start collapsed so the views get the room (the collapsed time panel keeps
    # its play bar for the 'step' timeline); every panel opens again from the top bar.
    return rrb.Blueprint(rrb.Tabs(*context_blueprint_parts(view), *extra_tabs),
                         rrb.BlueprintPanel(state="collapsed"),
                         rrb.SelectionPanel(state="collapsed"),
                         rrb.TimePanel(state="collapsed"))
