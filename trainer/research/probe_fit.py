"""The linear probes of protocad-probe: ridge regression from window-mean features to the true
log context (log m, log d), scored out of sample, numpy closed form.

Three settings, each asking a different question of the same windows:

* ``test_grid``: within the unseen (test) grid, grouped K-fold cross-validation by context
  (the windows of one context are never split between fitting and scoring, or the probe would
  only recognise the episode; the contexts are dealt to the folds in the order of the target,
  so that each fold spans its range);
* ``test_light`` / ``test_heavy``: the same inside one mass cluster of the test grid (m < 1,
  m > 1). The test masses come in two clusters, so a probe that only tells light from heavy
  already scores high on the whole grid; inside a cluster it has to read the value itself;
* ``train_to_test``: fitted on the training contexts' windows, scored on the test contexts'
  (extrapolation: every test value lies outside the training range).

The ridge penalty is chosen on the fitting part alone, by grouped cross-validation over its
contexts, so the scored windows never inform it. Scores: R^2 (1 - SS_res / SS_tot around the
scored windows' mean: negative when the probe is worse than that constant) and Spearman's rank
correlation (None where it is undefined: a constant prediction or target). Cross-validated, the
rank correlation is taken within each fold and averaged: pooled over folds it would rank each
fold's intercept too, and a probe that learned nothing predicts the other folds' mean, which
runs against its own fold's (about -0.4 for random features on the walker's test grid).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import spearmanr

ALPHAS = tuple(10.0 ** k for k in range(-3, 5))
DEFAULT_ALPHA = 1.0
FOLDS = 5
MIN_CONTEXTS = 3
SETTINGS = ("test_grid", "test_light", "test_heavy", "train_to_test")
#: A reference probe that knows only the mass cluster (m > 1) of each window: what a light/heavy
#: split alone scores within the test grid.
CLUSTER_FEATURE = "mass_cluster"


@dataclass
class Windows:
    """Window-mean features of both splits: features {name: (N, F)}, targets {name: (N,)},
    context (N,) index into `contexts`, split (N,) 'train' | 'test', mass (N,) true m."""

    features: dict[str, np.ndarray]
    targets: dict[str, np.ndarray]
    context: np.ndarray
    split: np.ndarray
    mass: np.ndarray

    def select(self, mask: np.ndarray) -> "Windows":
        return Windows({k: v[mask] for k, v in self.features.items()},
                       {k: v[mask] for k, v in self.targets.items()},
                       self.context[mask], self.split[mask], self.mass[mask])

    def __len__(self) -> int:
        return len(self.context)


# ----------------------------------------------------------------------------- ridge
def _standardize(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean = X.mean(0)
    std = X.std(0)
    # Features that do not vary on the fitting part carry nothing a linear probe could use.
    return mean, np.where(std > 1e-8, std, 1.0)


def ridge_path(X: np.ndarray, y: np.ndarray, Xq: np.ndarray, alphas: tuple[float, ...]) -> np.ndarray:
    """Predictions for Xq (M,) of ridge fits on standardized X (one SVD for all penalties):
    (len(alphas), M)."""
    mean, std = _standardize(X)
    Z, Zq = (X - mean) / std, (Xq - mean) / std
    y0 = y.mean()
    U, sv, Vt = np.linalg.svd(Z, full_matrices=False)
    Uy = U.T @ (y - y0)
    out = np.empty((len(alphas), len(Xq)))
    for i, alpha in enumerate(alphas):
        coef = Vt.T @ (sv / (sv ** 2 + alpha) * Uy)
        out[i] = y0 + Zq @ coef
    return out


def group_folds(groups: np.ndarray, k: int, seed: int = 0, y: np.ndarray | None = None) -> list[np.ndarray]:
    """The scored mask of each of min(k, #groups) folds of whole groups. With targets y the
    groups are dealt out in the order of their mean target (ties shuffled by seed), so every
    fold spans the range: with folds of random groups, a probe that has learned nothing
    predicts each fold's complement mean, which runs against the fold's own (a negative rank
    correlation out of nothing)."""
    uniq = np.unique(groups)
    order = np.random.default_rng(seed).permutation(len(uniq))
    if y is not None:
        means = np.array([y[groups == g].mean() for g in uniq])
        order = order[np.argsort(means[order], kind="stable")]
    n = min(k, len(uniq))
    return [np.isin(groups, uniq[order[f::n]]) for f in range(n)]


def choose_alpha(X: np.ndarray, y: np.ndarray, groups: np.ndarray, seed: int = 0) -> float:
    """The penalty with the least grouped cross-validated squared error on (X, y); the default
    where fewer than 3 groups leave nothing to validate on."""
    if len(np.unique(groups)) < 3:
        return DEFAULT_ALPHA
    err = np.zeros(len(ALPHAS))
    for scored in group_folds(groups, FOLDS, seed, y):
        pred = ridge_path(X[~scored], y[~scored], X[scored], ALPHAS)
        err += ((pred - y[scored]) ** 2).sum(1)
    return float(ALPHAS[int(np.argmin(err))])


def fit_predict(X: np.ndarray, y: np.ndarray, groups: np.ndarray, Xq: np.ndarray, seed: int = 0) -> np.ndarray:
    """Ridge fitted on (X, y) with its penalty chosen by grouped CV over `groups`; predicts Xq."""
    alpha = choose_alpha(X, y, groups, seed)
    return ridge_path(X, y, Xq, (alpha,))[0]


def grouped_cv_predict(X: np.ndarray, y: np.ndarray, groups: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Out-of-fold predictions (each window predicted by a probe that saw no window of its
    context) and the fold of each window."""
    pred, fold = np.empty(len(y)), np.empty(len(y), int)
    # At least 3 contexts in a fold where there are enough: the ranks are taken within folds.
    k = max(2, min(FOLDS, len(np.unique(groups)) // 3))
    for f, scored in enumerate(group_folds(groups, k, seed, y)):
        pred[scored] = fit_predict(X[~scored], y[~scored], groups[~scored], X[scored], seed)
        fold[scored] = f
    return pred, fold


# ----------------------------------------------------------------------------- scores
def r2_score(y: np.ndarray, pred: np.ndarray) -> float:
    ss_tot = float(((y - y.mean()) ** 2).sum())
    return 1.0 - float(((y - pred) ** 2).sum()) / ss_tot


def _constant(x: np.ndarray) -> bool:
    # A ridge fit on one target value predicts it up to rounding: ranks of rounding noise.
    return bool(np.ptp(x) <= 1e-9 * (1.0 + np.abs(x).max()))


def spearman(y: np.ndarray, pred: np.ndarray) -> float | None:
    if _constant(y) or _constant(pred):
        return None
    rho = float(spearmanr(y, pred).statistic)
    return rho if math.isfinite(rho) else None


def fold_spearman(y: np.ndarray, pred: np.ndarray, fold: np.ndarray) -> float | None:
    """Spearman's rank correlation within each fold, averaged with the folds' sizes as weights.
    Pooled over folds, the ranks would mix in each fold's intercept: a probe that learned
    nothing predicts the mean of the other folds, which runs against its own fold's."""
    rhos = [(spearman(y[fold == f], pred[fold == f]), int((fold == f).sum())) for f in np.unique(fold)]
    rhos = [(r, n) for r, n in rhos if r is not None]
    if not rhos:
        return None
    return float(sum(r * n for r, n in rhos) / sum(n for _, n in rhos))


def score(y: np.ndarray, pred: np.ndarray, groups: np.ndarray, fold: np.ndarray | None = None) -> dict:
    """R^2 over all scored windows; Spearman pooled, or within folds where they are given."""
    rho = spearman(y, pred) if fold is None else fold_spearman(y, pred, fold)
    return {"r2": r2_score(y, pred), "spearman": rho, "n_windows": int(len(y)),
            "n_contexts": int(len(np.unique(groups)))}


# ----------------------------------------------------------------------------- settings
def _scorable(w: Windows, target: str) -> str | None:
    """Why `w` cannot be cross-validated for `target` (None: it can)."""
    n_ctx = len(np.unique(w.context))
    if n_ctx < MIN_CONTEXTS:
        return f"{n_ctx} context(s): a probe needs at least {MIN_CONTEXTS} (2 to fit on when one is held out)"
    if np.ptp(w.targets[target]) == 0:
        return f"{target} takes one value here"
    return None


def _cv(X: np.ndarray, y: np.ndarray, groups: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pred, fold = grouped_cv_predict(X, y, groups, seed)
    return pred, groups, fold


def cross_validated(w: Windows, features: list[str], seed: int) -> tuple[dict, dict]:
    """{target: {feature: scores}} by grouped CV within `w`, and {target: why} where not."""
    out, skipped = {}, {}
    for target, y in w.targets.items():
        why = _scorable(w, target)
        if why:
            skipped[target] = why
            continue
        out[target] = {f: score(y, *_cv(w.features[f], y, w.context, seed)) for f in features}
    return out, skipped


def extrapolated(train: Windows, test: Windows, features: list[str], seed: int) -> tuple[dict, dict]:
    """{target: {feature: scores}} of probes fitted on `train`, scored on `test`."""
    out, skipped = {}, {}
    for target, y in test.targets.items():
        why = _scorable(train, target) or _scorable(test, target)
        if why:
            skipped[target] = why
            continue
        out[target] = {f: score(y, fit_predict(train.features[f], train.targets[target], train.context,
                                                test.features[f], seed), test.context)
                       for f in features}
    return out, skipped


def run_probes(w: Windows, seed: int = 0) -> tuple[dict, dict]:
    """probes[setting][target][feature] = {r2, spearman, n_windows, n_contexts} over the
    settings in SETTINGS that the windows allow, and skipped[setting] = {target: why} (or a
    string for the whole setting)."""
    feats = list(w.features)
    train, test = w.select(w.split == "train"), w.select(w.split == "test")
    probes: dict = {}
    skipped: dict = {}
    heavy = (test.mass > 1).astype(np.float64)[:, None]
    # The reference only where the grid has both clusters: a constant feature says nothing.
    grid_feats = feats + [CLUSTER_FEATURE] if len(np.unique(heavy)) == 2 else feats
    grid_w = Windows({**test.features, CLUSTER_FEATURE: heavy}, test.targets, test.context, test.split, test.mass)
    cases = {"test_grid": (grid_w, grid_feats),
             "test_light": (test.select(test.mass < 1), feats),
             "test_heavy": (test.select(test.mass > 1), feats)}
    for setting, (part, names) in cases.items():
        if not len(part):
            skipped[setting] = "no windows in this part of the test grid"
            continue
        probes[setting], why = cross_validated(part, names, seed)
        if why:
            skipped[setting] = why
    if len(train) and len(test):
        probes["train_to_test"], why = extrapolated(train, test, feats, seed)
        if why:
            skipped["train_to_test"] = why
    else:
        skipped["train_to_test"] = "needs windows of both splits"
    return {k: v for k, v in probes.items() if v}, skipped
