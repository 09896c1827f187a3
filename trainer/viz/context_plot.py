"""A static PNG of a context view (no viewer needed), drawn with PIL from the same numbers as the
rerun recording."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from trainer.viz.context_episodes import SPLIT_CLASS
from trainer.viz.context_view import CLASS_COLORS, CLASS_NAMES, PROTOTYPE_CLASS, ContextView, colormap

#: Panel titles of the feature spaces.
_FEATURE_TITLES = {"u_e": "learned feature (u, e)", "rssm_state": "RSSM state s", "u": "u", "e": "e"}


def _panel_colours(view: ContextView, col: str) -> tuple[np.ndarray, np.ndarray]:
    """Colours (points, context means) of a panel coloured ``col``: by_split or by_<param>."""
    eps, p_ep = view.episodes, view.point_episode
    if col == "by_split":
        split_col = np.array([CLASS_COLORS[SPLIT_CLASS[ep.split]] for ep in eps], np.uint8)
        ctx_split_col = np.array([CLASS_COLORS[SPLIT_CLASS[s]] for s, _ in view.contexts], np.uint8)
        return split_col[p_ep], ctx_split_col
    prm = col[3:]
    vlo, vhi = view.value_range[prm]
    pcol = colormap(np.array([ep.context.get(prm, np.nan) for ep in eps]), vlo, vhi)[p_ep]
    ccol = colormap(np.array([c.get(prm, np.nan) for _, c in view.contexts]), vlo, vhi)
    return pcol, ccol


def _draw_panel(draw, view: ContextView, feat: str, col: str, *, dim: int, x0: int, y0: int,
                panel: int, title_h: int, font) -> None:
    """One scatter of ``feat`` coloured ``col``: the points, the context means as big dots, the
    prototypes as red crosses."""
    Y = view.points[(feat, dim)]
    C = view.context_points[(feat, dim)]
    P = view.prototype_points.get((feat, dim))
    # Frame the points and the prototypes together: every prototype is drawn (a frame of
    # the points alone left all of them out in an early recording, hidden behind a note).
    framed = Y if P is None else np.concatenate([Y[:, :2], P[:, :2]])
    lo, hi = framed[:, :2].min(0), framed[:, :2].max(0)
    span = np.where(hi - lo > 1e-9, hi - lo, 1.0)
    top = y0 + title_h

    def px(Z: np.ndarray) -> np.ndarray:
        q = (Z[:, :2] - lo[:2]) / span[:2]
        return np.stack([x0 + 8 + q[:, 0] * (panel - 16),
                         top + panel - 8 - q[:, 1] * (panel - 16)], axis=1)

    draw.rectangle([x0, top, x0 + panel, top + panel], outline=(180, 180, 180))
    draw.text((x0 + 4, y0 + 6), f"{_FEATURE_TITLES.get(feat, feat)}, coloured {col.replace('_', ' ')}",
              fill="black", font=font)
    pcol, ccol = _panel_colours(view, col)
    P_xy = px(Y)
    for j in np.random.default_rng(0).permutation(len(view.point_episode)):
        x, y = P_xy[j]  # shuffled, so neither split paints over the other
        draw.ellipse([x - 2, y - 2, x + 2, y + 2], fill=tuple(int(v) for v in pcol[j]))
    for (x, y), rgb, (split, _) in zip(px(C), ccol, view.contexts):
        r = 6
        outline = (0, 0, 0) if split == "train" else (120, 120, 120)
        draw.ellipse([x - r, y - r, x + r, y + r], fill=tuple(int(v) for v in rgb),
                     outline=outline, width=2 if split == "test" else 1)
    if P is not None:
        for x, y in px(P):
            draw.line([x - 4, y - 4, x + 4, y + 4], fill=CLASS_COLORS[PROTOTYPE_CLASS], width=2)
            draw.line([x - 4, y + 4, x + 4, y - 4], fill=CLASS_COLORS[PROTOTYPE_CLASS], width=2)


def _draw_legends(draw, view: ContextView, cols: Sequence[str], *, ly: int, margin: int, panel: int,
                  font) -> None:
    """Under each column: a colour bar for a parameter, swatches for the split."""
    for c, col in enumerate(cols):
        x0 = margin + c * (panel + margin)
        if col == "by_split":
            x = x0
            for cls in (0, 1, 2):
                rgb = CLASS_COLORS[cls]
                if cls == 2:
                    draw.line([x, ly + 2, x + 10, ly + 12], fill=rgb, width=2)
                    draw.line([x, ly + 12, x + 10, ly + 2], fill=rgb, width=2)
                else:
                    draw.ellipse([x, ly + 2, x + 10, ly + 12], fill=rgb)
                draw.text((x + 14, ly), CLASS_NAMES[cls], fill="black", font=font)
                x += 100
            draw.text((x0, ly + 16), "big dots: per-context mean", fill="black", font=font)
        else:
            prm = col[3:]
            vlo, vhi = view.value_range[prm]
            ramp = colormap(np.linspace(0, 1, panel - 120), 0, 1)
            for i, rgb in enumerate(ramp):
                draw.line([x0 + 60 + i, ly, x0 + 60 + i, ly + 12], fill=tuple(int(v) for v in rgb))
            draw.text((x0, ly), f"{prm}={vlo:g}", fill="black", font=font)
            draw.text((x0 + panel - 56, ly), f"{vhi:g}", fill="black", font=font)
            draw.text((x0, ly + 16), "crosses: prototypes; grey ring: test context", fill="black",
                      font=font)


# ============================================================================== static PNG
def render_context_png(view: ContextView, path: str | Path, *, dim: int = 2, panel: int = 380,
                       features: Sequence[str] = ("u_e", "rssm_state")) -> Path:
    """A static scatter image of the 2D projection (no viewer needed), from the same numbers as
    the recording: rows = features (learned u,e and the RSSM state), columns = coloured by each
    context parameter, then by split; prototypes as red crosses, context means as big dots."""
    feats = [f for f in features if (f, dim) in view.points]
    if not feats:
        raise ValueError(f"no {dim}D projection of {list(features)} in this view")
    cols = [f"by_{p}" for p in view.params] + ["by_split"]
    title_h, margin, bar_h = 28, 14, 34
    W = margin + len(cols) * (panel + margin)
    H = title_h + len(feats) * (panel + title_h + margin) + bar_h + margin
    img = Image.new("RGB", (W, H), "white")
    draw = ImageDraw.Draw(img)
    font = ImageFont.load_default(size=15)
    n_ctx = view.contexts_per_split()
    draw.text((margin, 6), f"Context features, {view.method.upper()} {dim}D: {len(view.episodes)} "
              f"episodes of {n_ctx['train']} train and {n_ctx['test']} test contexts, "
              f"K={view.num_prototypes} prototypes", fill="black", font=font)
    for r, feat in enumerate(feats):
        for c, col in enumerate(cols):
            _draw_panel(draw, view, feat, col, dim=dim, x0=margin + c * (panel + margin),
                        y0=title_h + r * (panel + title_h + margin), panel=panel, title_h=title_h,
                        font=font)
    _draw_legends(draw, view, cols, ly=H - bar_h - margin + 4, margin=margin, panel=panel,
                  font=ImageFont.load_default(size=12))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)
    return path
