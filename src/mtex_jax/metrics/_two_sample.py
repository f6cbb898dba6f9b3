"""A classifier two-sample test: can a classifier tell generated motion from real motion?

The W₁ ratios of :func:`~mtex_jax.metrics.realism` compare one-dimensional marginals (one
joint's speed at a time); a classifier sees joint structure: poses, coordination and rhythm
together. The test (design §10.4) is the "discriminative score" of time-series generators:

1. every clip is cut into windows of ``window`` seconds (non-overlapping, from its first
   frame);
2. each window becomes one feature vector (:func:`window_features`): the world joint positions
   relative to the root at ``samples`` evenly spaced frames, in the heading frame of the
   window's first frame (rotated about the up axis so that the root faces the first ground
   axis), plus each joint's speed mean and spread over the window;
3. a gradient-boosted tree classifier (scikit-learn's ``HistGradientBoostingClassifier``)
   learns to tell the two sets apart, and its ROC AUC is measured by stratified k-fold
   cross-validation, the windows grouped into contiguous blocks of their clip so that
   neighbouring windows, which look alike, do not sit on both sides of a split.

An AUC of 0.5 means the classifier cannot tell the sets apart; 1 means it always can. Real
motion of another take is itself distinguishable to some degree, so the AUC of generated
motion is read beside a real-against-real reference computed the same way
(:attr:`TwoSampleResult.reference_auc`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from ..motion import Motion, as_motion_list, ground_axes, joint_positions, quat_rotate

__all__ = ["TwoSampleResult", "two_sample_auc", "window_features"]

_INSTALL = 'pip install -e ".[metrics]"'


@dataclasses.dataclass(frozen=True)
class TwoSampleResult:
    """Cross-validated AUC of a classifier telling ``generated`` from ``real`` windows.

    Attributes:
        auc: mean ROC AUC over the folds (0.5: indistinguishable).
        auc_std: its standard deviation over the folds.
        fold_aucs: the AUC of each fold.
        reference_auc: the same test of ``reference`` against ``real`` (real against real),
            or ``None`` without a reference.
        reference_std: its standard deviation over the folds, or ``None``.
        n_real: windows of the real set.
        n_generated: windows of the generated set.
        window: window length (seconds).
        folds: number of folds.
        seed: seed of the folds and the classifier.
    """

    auc: float
    auc_std: float
    fold_aucs: tuple[float, ...]
    reference_auc: float | None
    reference_std: float | None
    n_real: int
    n_generated: int
    window: float
    folds: int
    seed: int

    def as_dict(self) -> dict[str, object]:
        """Plain JSON-ready numbers."""
        d = dataclasses.asdict(self)
        d["fold_aucs"] = list(self.fold_aucs)
        return d


def _window_frames(window: float, fps: float, where: str) -> int:
    if isinstance(window, bool) or not isinstance(window, int | float) or not np.isfinite(window):
        raise ValueError(f"{where}: window must be a positive number of seconds, got {window!r}")
    n = round(float(window) * fps)
    if n < 4:
        raise ValueError(
            f"{where}: window = {window} s is {n} frames at {fps:g} Hz; it needs at least 4"
        )
    return n


def window_features(
    motions: Motion | Sequence[Motion], window: float = 2.0, samples: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """The feature vector of every non-overlapping window of every clip (design §10.4).

    For a window of ``W`` frames starting at frame ``s``: the joint positions ``p_t − r_t``
    (``r_t`` the root joint) at ``samples`` frames evenly spaced over the window, rotated
    about the up axis by minus the heading of the root at frame ``s`` (the horizontal
    direction that the root's rotation takes the first ground axis to), flattened; then each
    joint's speed ``|p_{t+1} − p_t| f`` averaged over the window, then its standard deviation.
    The features are thus invariant to where the dancer is and which way they face.

    Args:
        motions: clips of one skeleton at one frame rate.
        window: window length in seconds (at least 4 frames).
        samples: pose samples per window, ``2 ≤ samples ≤`` the window's frames.

    Returns:
        ``(n, samples·J·3 + 2J)`` features and ``(n,)`` the clip index of each window.

    Raises:
        ValueError: different skeletons or frame rates, bad ``window`` or ``samples``, or
            no clip long enough for one window.
    """
    where = "window_features"
    ms = as_motion_list(motions, where)
    fps = ms[0].fps
    if any(m.fps != fps for m in ms):
        raise ValueError(
            f"{where}: the clips have different frame rates "
            f"({sorted({m.fps for m in ms})}); resample them first (Motion.resample)"
        )
    W = _window_frames(window, fps, where)
    if isinstance(samples, bool) or not isinstance(samples, int) or not 2 <= samples <= W:
        raise ValueError(f"{where}: samples must be an int in 2..{W}, got {samples!r}")
    sk = ms[0].skeleton
    _, h0, h1 = ground_axes(sk.up_axis)
    e0 = np.zeros(3)
    e0[h0] = 1.0
    picks = np.round(np.linspace(0, W - 1, samples)).astype(np.int64)
    feats, clip_of = [], []
    positions = joint_positions(ms, None, min_frames=1, where=where)
    for c, (m, p) in enumerate(zip(ms, positions, strict=True)):
        n_win = m.n_frames // W
        if n_win == 0:
            continue
        starts = np.arange(n_win) * W
        q0 = np.asarray(m.rotations)[starts, 0]
        fwd = np.asarray(quat_rotate(q0, np.broadcast_to(e0, (n_win, 3))))
        ang = np.arctan2(fwd[:, h1], fwd[:, h0])  # heading about up, from h0 towards h1
        cos, sin = np.cos(-ang), np.sin(-ang)
        for i, s in enumerate(starts):
            win = p[s : s + W]  # (W, J, 3)
            rel = win[picks] - win[picks, :1]
            turned = rel.copy()
            turned[..., h0] = cos[i] * rel[..., h0] - sin[i] * rel[..., h1]
            turned[..., h1] = sin[i] * rel[..., h0] + cos[i] * rel[..., h1]
            speed = np.linalg.norm(np.diff(win, axis=0), axis=-1) * fps  # (W−1, J)
            feats.append(np.concatenate([turned.ravel(), speed.mean(0), speed.std(0)]))
            clip_of.append(c)
    if not feats:
        longest = max(m.n_frames for m in ms)
        raise ValueError(
            f"{where}: no clip holds one window of {W} frames (the longest has {longest})"
        )
    return np.stack(feats), np.asarray(clip_of, dtype=np.int64)


def _blocks(clip_of: np.ndarray, folds: int) -> np.ndarray:
    """Each clip's windows in up to ``folds`` contiguous blocks: the group of each window."""
    groups = np.empty_like(clip_of)
    next_id = 0
    for c in np.unique(clip_of):
        idx = np.flatnonzero(clip_of == c)
        block = np.arange(idx.size) * min(folds, idx.size) // idx.size
        groups[idx] = next_id + block
        next_id += int(block.max()) + 1
    return groups


def _cv_auc(
    a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray], folds: int, seed: int
) -> np.ndarray:
    from sklearn.ensemble import HistGradientBoostingClassifier
    from sklearn.metrics import roc_auc_score
    from sklearn.model_selection import StratifiedGroupKFold

    X = np.concatenate([a[0], b[0]])
    y = np.concatenate([np.zeros(len(a[0]), np.int64), np.ones(len(b[0]), np.int64)])
    ga = _blocks(a[1], folds)
    groups = np.concatenate([ga, ga.max() + 1 + _blocks(b[1], folds)])
    splitter = StratifiedGroupKFold(n_splits=folds, shuffle=True, random_state=seed)
    aucs = []
    for train, test in splitter.split(X, y, groups):
        if np.unique(y[test]).size < 2 or np.unique(y[train]).size < 2:
            raise ValueError(
                "two_sample_auc: a fold holds windows of one set only; give more or longer "
                "clips, or fewer folds"
            )
        # scikit-learn's default leaf of 20 windows leaves a few dozen windows unsplit (a
        # constant prediction, AUC 0.5 whatever the motion): leaves of one twentieth of the
        # training windows, between 3 and 20
        leaf = int(np.clip(len(train) // 20, 3, 20))
        clf = HistGradientBoostingClassifier(min_samples_leaf=leaf, random_state=seed)
        clf.fit(X[train], y[train])
        aucs.append(roc_auc_score(y[test], clf.predict_proba(X[test])[:, 1]))
    return np.asarray(aucs)


def two_sample_auc(
    real: Motion | Sequence[Motion],
    generated: Motion | Sequence[Motion],
    *,
    reference: Motion | Sequence[Motion] | None = None,
    window: float = 2.0,
    folds: int = 5,
    seed: int = 0,
    samples: int = 8,
) -> TwoSampleResult:
    """Classifier two-sample test of ``generated`` against ``real`` motion (design §10.4).

    Windows of both sets (:func:`window_features`) are told apart by scikit-learn's
    ``HistGradientBoostingClassifier`` (its defaults but for leaves of at least one twentieth
    of the training windows, between 3 and 20, and ``random_state=seed``); the ROC AUC
    is measured by ``folds``-fold stratified cross-validation whose groups are contiguous
    blocks of each clip's windows. With ``reference`` (other real motion, e.g. the training
    clips when ``real`` is held out), the same test of ``reference`` against ``real`` is run
    beside it: the AUC that real dancing itself scores.

    Args:
        real: the real clips.
        generated: the clips to judge, of the same skeleton and frame rate.
        reference: other real clips, or ``None``.
        window: window length in seconds.
        folds: cross-validation folds, ``≥ 2``; each set needs at least ``folds`` windows.
        seed: seed of the folds and of the classifier (the result is deterministic).
        samples: pose samples per window.

    Returns:
        A :class:`TwoSampleResult`.

    Raises:
        ImportError: scikit-learn is not installed (the ``metrics`` extra).
        ValueError: different skeletons or frame rates, too few windows, bad arguments.
    """
    where = "two_sample_auc"
    try:
        import sklearn  # noqa: F401
    except ImportError as e:  # pragma: no cover - exercised only without the extra
        raise ImportError(f"{where} needs scikit-learn: {_INSTALL}") from e
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 2:
        raise ValueError(f"{where}: folds must be an int ≥ 2, got {folds!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**32:
        raise ValueError(f"{where}: seed must be an int in [0, 2³²), got {seed!r}")
    sets = {"real": real, "generated": generated}
    if reference is not None:
        sets["reference"] = reference
    lists = {k: as_motion_list(v, f"{where}: {k}") for k, v in sets.items()}
    first = lists["real"][0]
    for k, ms in lists.items():
        for m in ms:
            if not m.skeleton.same_structure(first.skeleton):
                raise ValueError(f"{where}: the {k} clips' skeleton is not the real clips'")
            if m.fps != first.fps:
                raise ValueError(
                    f"{where}: the {k} clips are at {m.fps:g} Hz, the real ones at "
                    f"{first.fps:g} Hz; resample them first (Motion.resample)"
                )
    feats = {k: window_features(ms, window, samples) for k, ms in lists.items()}
    for k, (X, _) in feats.items():
        if len(X) < folds:
            raise ValueError(
                f"{where}: the {k} clips give {len(X)} window{'s' * (len(X) != 1)} of "
                f"{window} s, fewer than folds = {folds}"
            )
    aucs = _cv_auc(feats["real"], feats["generated"], folds, seed)
    ref = _cv_auc(feats["real"], feats["reference"], folds, seed) if reference is not None else None
    return TwoSampleResult(
        auc=float(aucs.mean()),
        auc_std=float(aucs.std()),
        fold_aucs=tuple(float(a) for a in aucs),
        reference_auc=None if ref is None else float(ref.mean()),
        reference_std=None if ref is None else float(ref.std()),
        n_real=len(feats["real"][0]),
        n_generated=len(feats["generated"][0]),
        window=float(window),
        folds=folds,
        seed=seed,
    )
