"""How one bag's messages become the store's steps (trainer/data/dataset.py, "How it rebuilds
episodes"): BagColumns keeps what each mapped topic brought while the bag streams by; assemble
pairs frames with step_infos, finds each observation's answer and context, and cuts episodes
and segments, counting into the source's report everything that did not fit."""
from __future__ import annotations

from array import array
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sim_bridge.contract import camera
from sim_bridge.contract import topics as T
from trainer.data.records import REQUIRED_KEYS, ImageSpec, SourceReport


@dataclass
class BagColumns:
    """What one pass over a bag kept of each mapped topic, in arrival order: stamps and flat
    values (frames go straight to images.u8). assemble() deduplicates and aligns them."""

    img_stamps: array = field(default_factory=lambda: array("q"))
    si_stamps: array = field(default_factory=lambda: array("q"))
    si_vals: array = field(default_factory=lambda: array("d"))
    act_stamps: array = field(default_factory=lambda: array("q"))
    act_vals: array = field(default_factory=lambda: array("d"))
    ctx_stamps: array = field(default_factory=lambda: array("q"))
    ctx_vals: array = field(default_factory=lambda: array("d"))
    act_dim: int | None = None
    action_names: list[str] | None = None
    ctx_names: list[str] | None = None
    hw: tuple[int, int] | None = None
    n_img: int = 0
    seen_img: set[int] = field(default_factory=set)
    dup: dict[str, int] = field(default_factory=dict)
    decode_errors: dict[str, int] = field(default_factory=dict)
    image: ImageSpec = field(default_factory=ImageSpec)

    def take(self, key: str, topic: str, msg: Any, img_f: Any) -> None:
        """Keep one decoded message; raises (ValueError...) for a message to count as undecodable."""
        stamp = T.stamp_to_ns(msg.header.stamp)
        if key == "image":
            self._take_image(topic, msg, stamp, img_f)
        elif key == "step_info":
            info = T.read_step_info(msg)
            self.si_stamps.append(stamp)
            self.si_vals.extend([float(info.reward), float(info.discount), float(info.is_first),
                                 float(info.is_last), float(info.is_terminal), float(info.episode),
                                 float(info.step)])
        elif key == "action":
            self._take_action(msg, stamp)
        elif key == "context":
            names = [str(n) for n in msg.name]
            if self.ctx_names is None:
                self.ctx_names = names
            if names != self.ctx_names:
                raise ValueError(f"context names {names} differ from earlier {self.ctx_names}")
            self.ctx_stamps.append(stamp)
            self.ctx_vals.extend(float(v) for v in msg.position)

    def _take_image(self, topic: str, msg: Any, stamp: int, img_f: Any) -> None:
        # Frames are written as they arrive, so a republished stamp is dropped here, not later.
        if stamp in self.seen_img:
            self.dup[topic] = self.dup.get(topic, 0) + 1
            return
        # The policy node's own function: a frame at the model's size passes bit-exact.
        img = camera.model_image(msg, self.image.size, camera.Crop.parse(self.image.crop))
        if self.hw is None:
            self.hw = (img.shape[0], img.shape[1])
        img_f.write(np.ascontiguousarray(img).tobytes())
        self.seen_img.add(stamp)
        self.img_stamps.append(stamp)
        self.n_img += 1

    def _take_action(self, msg: Any, stamp: int) -> None:
        a = T.read_action(msg)
        if not np.all(np.isfinite(a)):
            raise ValueError("non-finite action")
        if self.act_dim is None:
            self.act_dim = int(a.size)
            self.action_names = [str(n) for n in msg.name]
        if a.size != self.act_dim:
            raise ValueError(f"action has {a.size} values, earlier ones {self.act_dim}")
        self.act_stamps.append(stamp)
        self.act_vals.extend(a.tolist())


def _dedup(stamps: array, name: str, dup: dict) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique stamps and the index of each one's FIRST occurrence in stream order."""
    s = np.frombuffer(stamps, dtype=np.int64) if len(stamps) else np.zeros(0, np.int64)
    u, first = np.unique(s, return_index=True)
    if s.size - u.size:
        dup[name] = dup.get(name, 0) + int(s.size - u.size)
    return u, first


@dataclass
class _Steps:
    """The observations that have both a frame and a step_info, in stamp order."""

    stamps: np.ndarray
    img_row: np.ndarray
    reward: np.ndarray
    discount: np.ndarray
    is_first: np.ndarray
    is_last: np.ndarray
    is_terminal: np.ndarray
    episode: np.ndarray
    step: np.ndarray

    @property
    def n(self) -> int:
        return int(self.stamps.size)


@dataclass
class _Boundaries:
    """Per step: where an episode starts, and the breaks that start a new segment inside one."""

    new_ep: np.ndarray
    gap: np.ndarray            # step ids missing before this step
    out_of_order: np.ndarray   # step id not after the previous one
    missing_prev: np.ndarray   # the previous observation has no answer
    seg_start: np.ndarray


def assemble(rep: SourceReport, st: BagColumns, by_key: dict[str, str]) -> tuple[dict[str, np.ndarray], dict]:
    """The store's per-step arrays and index (segments, episodes) from what the bag streamed,
    with the counts of everything that did not fit into the source's report."""
    steps = _align_observations(rep, st, by_key)
    if steps is None:
        return {}, {"num_steps": 0, "segments": [], "episodes": []}
    n = steps.n
    answer, has_act = _answers(rep, st, by_key, steps.stamps)
    ctx = _context_at(rep, st, by_key, steps.stamps)
    b = _boundaries(rep, steps, has_act)

    # training convention: action[t] = answer to obs t-1 within a segment, zeros at its start
    action = np.zeros((n, st.act_dim), np.float32)
    cont = ~b.seg_start
    action[1:][cont[1:]] = answer[:-1][cont[1:]]

    starts = np.flatnonzero(b.seg_start)
    segments = np.stack([starts, np.diff(np.r_[starts, n])], 1)
    rep.segments = int(starts.size)
    episodes = _episode_index(rep, steps, b, ctx, st.ctx_names)

    arrays = {"stamp": steps.stamps.astype(np.int64), "img_row": steps.img_row.astype(np.int64),
              "action": action, "reward": steps.reward, "discount": steps.discount,
              "is_first": steps.is_first, "is_last": steps.is_last, "is_terminal": steps.is_terminal,
              "episode": steps.episode, "step": steps.step}
    if ctx is not None:
        arrays["context"] = ctx
    meta = {"num_steps": n, "segments": segments.tolist(), "episodes": episodes, "context_names": st.ctx_names}
    return arrays, meta


def _align_observations(rep: SourceReport, st: BagColumns, by_key: dict[str, str]) -> _Steps | None:
    """Pair frames with step_infos by header.stamp; None (and rep.rejected says why) when a
    required topic brought nothing usable or no stamp has both."""
    # images: already deduplicated while streaming (row = arrival order)
    img_s = np.frombuffer(st.img_stamps, dtype=np.int64) if len(st.img_stamps) else np.zeros(0, np.int64)
    img_order = np.argsort(img_s, kind="stable")
    img_sorted, img_rows = img_s[img_order], img_order.astype(np.int64)
    si_u, si_first = _dedup(st.si_stamps, by_key["step_info"], st.dup)
    si = (np.frombuffer(st.si_vals, dtype=np.float64).reshape(-1, 7)[si_first] if len(st.si_vals)
          else np.zeros((0, 7)))
    rep.duplicates = {t: n for t, n in st.dup.items() if n}

    got = {"image": len(st.img_stamps), "step_info": len(st.si_stamps), "action": len(st.act_stamps)}
    missing = [k for k in REQUIRED_KEYS if not got[k]]
    if missing:
        rep.rejected = ("no usable messages for " + ", ".join(f"{k} ({by_key[k]})" for k in missing)
                        + "; map topics with --topic KEY=/name")
        return None

    stamps, i_img, i_si = np.intersect1d(img_sorted, si_u, assume_unique=True, return_indices=True)
    rep.images_without_step_info = int(img_sorted.size - stamps.size)
    rep.step_info_without_image = int(si_u.size - stamps.size)
    if stamps.size == 0:
        rep.rejected = "no step has both an image and a step_info with the same header.stamp"
        return None
    rep.steps = int(stamps.size)
    si = si[i_si]
    return _Steps(stamps=stamps, img_row=img_rows[i_img],
                  reward=si[:, 0].astype(np.float32), discount=si[:, 1].astype(np.float32),
                  is_first=si[:, 2] > 0.5, is_last=si[:, 3] > 0.5, is_terminal=si[:, 4] > 0.5,
                  episode=si[:, 5].astype(np.int64), step=si[:, 6].astype(np.int64))


def _answers(rep: SourceReport, st: BagColumns, by_key: dict[str, str],
             stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The action answering each observation (same stamp; zeros where none did) and which had one."""
    act_u, act_first = _dedup(st.act_stamps, by_key["action"], st.dup)
    rep.duplicates = {t: k for t, k in st.dup.items() if k}
    acts = np.frombuffer(st.act_vals, dtype=np.float64).reshape(-1, st.act_dim)[act_first]
    pos = np.searchsorted(act_u, stamps)
    pos_c = np.minimum(pos, max(act_u.size - 1, 0))
    has_act = (act_u.size > 0) & (act_u[pos_c] == stamps)
    answer = np.zeros((stamps.size, st.act_dim), np.float32)
    answer[has_act] = acts[pos_c[has_act]]
    rep.orphan_actions = int(act_u.size - np.count_nonzero(has_act))
    return answer, has_act


def _context_at(rep: SourceReport, st: BagColumns, by_key: dict[str, str], stamps: np.ndarray) -> np.ndarray | None:
    """The context in force at each observation (the last one published at or before its
    stamp; NaN before the first), None for a bag without context."""
    if st.ctx_names is None or not len(st.ctx_stamps):
        return None
    ctx_u, ctx_first = _dedup(st.ctx_stamps, by_key.get("context", "context"), st.dup)
    rep.duplicates = {t: k for t, k in st.dup.items() if k}
    cv = np.frombuffer(st.ctx_vals, dtype=np.float64).reshape(-1, len(st.ctx_names))[ctx_first]
    cpos = np.searchsorted(ctx_u, stamps, side="right") - 1
    ctx = np.full((stamps.size, len(st.ctx_names)), np.nan, np.float32)
    ok = cpos >= 0
    ctx[ok] = cv[cpos[ok]]
    return ctx


def _boundaries(rep: SourceReport, steps: _Steps, has_act: np.ndarray) -> _Boundaries:
    """Episode starts, and segment breaks inside episodes: missing step ids (a gap), step ids
    going backwards, an observation whose predecessor has no answer (its action is unknown)."""
    episode, step = steps.episode, steps.step
    prev_ep = np.r_[np.int64(-(2 ** 62)), episode[:-1]]
    new_ep = steps.is_first | (episode != prev_ep)
    new_ep[0] = True
    dstep = np.r_[1, np.diff(step)]
    gap = (~new_ep) & (dstep > 1)
    ooo = (~new_ep) & (dstep < 1)
    prev_has_act = np.r_[False, has_act[:-1]]
    miss_prev = (~new_ep) & (~gap) & (~ooo) & (~prev_has_act)
    rep.gaps = int(gap.sum())
    rep.missing_step_ids = int((dstep[gap] - 1).sum())
    for i in np.flatnonzero(gap)[:20]:
        a, b = step[i - 1] + 1, step[i] - 1
        rep.gap_examples.append(f"episode {episode[i]} steps {a}" + (f"..{b}" if b > a else ""))
    rep.out_of_order = int(ooo.sum())
    rep.missing_actions = int(miss_prev.sum())
    last = steps.n - 1
    rep.unanswered_final = int(not has_act[last] and not steps.is_last[last])
    rep.unanswered_is_last = int(np.count_nonzero(steps.is_last & ~has_act))
    return _Boundaries(new_ep=new_ep, gap=gap, out_of_order=ooo, missing_prev=miss_prev,
                       seg_start=new_ep | gap | ooo | miss_prev)


def _episode_index(rep: SourceReport, steps: _Steps, b: _Boundaries, ctx: np.ndarray | None,
                   ctx_names: list[str] | None) -> list[dict]:
    """One entry per episode: where it lies, whether it is whole, its return, its context and split."""
    ep_starts = np.flatnonzero(b.new_ep)
    ep_lens = np.diff(np.r_[ep_starts, steps.n])
    is_first = steps.is_first
    episodes = []
    split_idx = ctx_names.index(T.SPLIT_FIELD) if ctx_names and T.SPLIT_FIELD in ctx_names else None
    for s0, ln in zip(ep_starts.tolist(), ep_lens.tolist()):
        sl = slice(s0, s0 + ln)
        e = {"start": s0, "length": ln, "episode": int(steps.episode[s0]), "has_first": bool(is_first[s0]),
             "has_last": bool(steps.is_last[s0 + ln - 1]),
             "gaps": int(b.gap[sl].sum() + b.out_of_order[sl].sum() + b.missing_prev[sl].sum()),
             "return": float(steps.reward[sl][~is_first[sl]].sum()), "context": None, "split": None}
        if ctx is not None:
            row = ctx[s0]
            if np.all(np.isfinite(row)):
                e["context"] = {k: float(v) for k, v in zip(ctx_names, row) if k != T.SPLIT_FIELD}
                if split_idx is not None:
                    e["split"] = T.SPLITS[int(row[split_idx])] if int(row[split_idx]) in (0, 1) else None
        episodes.append(e)
    rep.episodes = len(episodes)
    rep.episodes_without_first = sum(not e["has_first"] for e in episodes)
    rep.complete_episodes = sum(e["has_first"] and e["has_last"] and not e["gaps"] for e in episodes)
    return episodes
