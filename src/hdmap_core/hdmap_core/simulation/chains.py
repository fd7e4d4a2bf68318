"""Synthetic per-step observations with known per-drive offsets, for testing the adjustment.

A one-directional road of ``road_length_m`` carries fixed lines at lateral positions
``line_offsets_m``. Drives cover random intervals of the road (so they overlap each other in
chains: A overlaps B overlaps C ...). Each drive has a localization error made of a constant bias
``N(0, bias_sigma_m^2)`` plus a first-order Gauss-Markov drift (stationary sigma ``drift_sigma_m``,
correlation length ``correlation_length_m``), the error model of ``simulate.py``. A sampling step
every ``step_spacing_m`` sees the drives that cover it; each drive observes each line with
probability ``detect_prob``.

Sign convention: a drive whose pose is shifted left by ``e`` sees every feature ``e`` further
left, so ``lateral = x_true + e + noise``; the correction to ADD is ``-e``, stored in
``SimTruth.correction``. The cut of every step is shifted by a random amount (the pivot's own
error), which the adjustment must treat as a nuisance.

Only the 1-D lateral geometry matters to the adjustment, so the road is straight along x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hdmap_core.model import FeatureType
from hdmap_core.steps import StepObservations

__all__ = ["ChainSimConfig", "SimTruth", "simulate_step_observations", "StepObservations"]


@dataclass(frozen=True)
class ChainSimConfig:
    """Parameters of the synthetic chain of drives (lengths in metres).

    Attributes:
        road_length_m: length of the road.
        n_drives: number of drives.
        drive_length_min_m / drive_length_max_m: uniform range of drive lengths.
        step_spacing_m: distance between sampling steps along the road.
        line_offsets_m: lateral positions of the lines (+ = left).
        line_types: FeatureType code of each line.
        detect_prob: probability that a drive observes a line at a step.
        line_detect_prob: per-line probabilities instead (empty = ``detect_prob`` for all).
        bias_sigma_m: sigma of the constant lateral bias per drive.
        zero_mean_bias: subtract the fleet mean from the drawn biases (gauge test).
        drift_sigma_m: stationary sigma of the Gauss-Markov drift (0 = none).
        correlation_length_m: correlation length of the drift.
        noise_sigma_m: per-sample measurement noise.
        cut_shift_sigma_m: sigma of the per-step shift of the cut (nuisance).
        wrong_label_fraction: share of samples whose cluster label is swapped to a neighbouring line.
        wrong_label_burst_m: 0 = wrong labels are independent per sample; > 0 = they come in
            stretches of this length per drive (one line, one direction per stretch, as a
            misclassification persisting along a drive does), covering about the same share.
        s_start_max_m: each drive's travelled distance starts at uniform [0, this) (not 0).
    """

    road_length_m: float = 20000.0
    n_drives: int = 60
    drive_length_min_m: float = 2000.0
    drive_length_max_m: float = 6000.0
    step_spacing_m: float = 20.0
    line_offsets_m: tuple[float, ...] = (-5.6, -1.75, 1.75, 5.25, 6.2)
    line_types: tuple[int, ...] = (
        int(FeatureType.ROAD_BORDER),
        int(FeatureType.DASHED),
        int(FeatureType.DASHED),
        int(FeatureType.SOLID),
        int(FeatureType.ROAD_BORDER),
    )
    detect_prob: float = 0.7
    line_detect_prob: tuple[float, ...] = ()
    bias_sigma_m: float = 1.0
    zero_mean_bias: bool = False
    drift_sigma_m: float = 0.3
    correlation_length_m: float = 1000.0
    noise_sigma_m: float = 0.1
    cut_shift_sigma_m: float = 1.0
    wrong_label_fraction: float = 0.0
    wrong_label_burst_m: float = 0.0
    s_start_max_m: float = 500.0


@dataclass(frozen=True)
class SimTruth:
    """The known answer of a simulation.

    Attributes:
        drive_ids: (D,) ids.
        start_m: (D,) road position where each drive starts.
        s0_m: (D,) travelled distance at the drive's start.
        grid_s_m: list of (G_d,) travelled distances of each drive's truth grid (1 m).
        correction: list of (G_d,) true correction to add [m] on that grid.
    """

    drive_ids: tuple[str, ...]
    start_m: np.ndarray
    s0_m: np.ndarray
    grid_s_m: list[np.ndarray]
    correction: list[np.ndarray]

    def true_correction(self, drive_id: str, s_m: np.ndarray) -> np.ndarray:
        """The true correction of ``drive_id`` at travelled distances ``s_m`` (linear interp.)."""
        d = self.drive_ids.index(drive_id)
        return np.interp(s_m, self.grid_s_m[d], self.correction[d])


def _gauss_markov(n: int, step_m: float, sigma_m: float, corr_m: float, rng: np.random.Generator) -> np.ndarray:
    """(n,) stationary first-order Gauss-Markov sequence sampled every ``step_m``."""
    if sigma_m <= 0.0:
        return np.zeros(n)
    phi = np.exp(-step_m / corr_m)
    innov = rng.normal(0.0, sigma_m * np.sqrt(1.0 - phi**2), n)
    innov[0] = rng.normal(0.0, sigma_m)
    out = np.empty(n)
    acc = 0.0
    for i in range(n):  # 1-m grid of a few km per drive: cheap
        acc = phi * acc + innov[i] if i else innov[0]
        out[i] = acc
    return out


def simulate_step_observations(
    *, config: ChainSimConfig = ChainSimConfig(), seed: int = 0
) -> tuple[list[StepObservations], SimTruth]:
    """Build per-step observations of a chain of overlapping drives with known offsets.

    Returns:
        (observations, truth): one StepObservations per step that at least one drive covers;
        cluster labels are the true line index except for the swapped ``wrong_label_fraction``.
    """
    cfg = config
    rng = np.random.default_rng(seed)
    n_lines = len(cfg.line_offsets_m)
    lines = np.asarray(cfg.line_offsets_m, dtype=float)
    types = np.asarray(cfg.line_types, dtype=np.int64)
    lengths = rng.uniform(cfg.drive_length_min_m, cfg.drive_length_max_m, cfg.n_drives)
    starts = rng.uniform(-0.3 * lengths, cfg.road_length_m - 0.7 * lengths)
    s0 = rng.uniform(0.0, cfg.s_start_max_m, cfg.n_drives)
    biases = rng.normal(0.0, cfg.bias_sigma_m, cfg.n_drives)
    if cfg.zero_mean_bias:
        biases -= biases.mean()
    ids = tuple(f"drive_{i:03d}" for i in range(cfg.n_drives))
    grids, corrs = [], []
    for i in range(cfg.n_drives):
        g = np.arange(0.0, lengths[i] + 1.0, 1.0)
        err = biases[i] + _gauss_markov(len(g), 1.0, cfg.drift_sigma_m, cfg.correlation_length_m, rng)
        grids.append(s0[i] + g)
        corrs.append(-err)
    truth = SimTruth(ids, starts, s0, grids, corrs)
    # bursts of wrong labels: per drive, stretches [u, u + burst) with one line and one direction
    n_burst = (
        np.round(cfg.wrong_label_fraction * n_lines * lengths / cfg.wrong_label_burst_m).astype(int)
        if cfg.wrong_label_burst_m > 0
        else np.zeros(cfg.n_drives, dtype=int)
    )
    bursts = [
        (
            starts[i] + rng.uniform(0.0, lengths[i], n_burst[i]),
            rng.integers(0, n_lines, n_burst[i]),
            np.where(rng.random(n_burst[i]) < 0.5, -1, 1),
        )
        for i in range(cfg.n_drives)
    ]

    obs: list[StepObservations] = []
    for j, u in enumerate(np.arange(0.0, cfg.road_length_m, cfg.step_spacing_m)):
        present = np.flatnonzero((starts <= u) & (u <= starts + lengths))
        if present.size == 0:
            continue
        seen = rng.random((present.size, n_lines)) < (
            np.asarray(cfg.line_detect_prob) if cfg.line_detect_prob else cfg.detect_prob
        )
        di, li = np.nonzero(seen)
        drv = present[di]
        s = s0[drv] + (u - starts[drv])
        s_present = s0[present] + (u - starts[present])
        err_present = -np.array([np.interp(sp, grids[d], corrs[d]) for sp, d in zip(s_present, present)])
        err = err_present[di]
        shift = rng.normal(0.0, cfg.cut_shift_sigma_m)
        lat = lines[li] + shift + err + rng.normal(0.0, cfg.noise_sigma_m, li.size)
        label = li.copy()
        if cfg.wrong_label_burst_m > 0:
            wrong = np.zeros(li.size, dtype=bool)
            step_dir = np.ones(li.size, dtype=np.int64)
            for k, (d, line) in enumerate(zip(drv, li)):  # ~50 samples per step
                b_start, b_line, b_dir = bursts[d]
                hit = (b_start <= u) & (u < b_start + cfg.wrong_label_burst_m) & (b_line == line)
                if hit.any():
                    wrong[k] = True
                    step_dir[k] = b_dir[np.argmax(hit)]
        else:
            wrong = rng.random(li.size) < cfg.wrong_label_fraction
            step_dir = np.where(rng.random(li.size) < 0.5, -1, 1)
        label[wrong] = np.clip(li[wrong] + step_dir[wrong], 0, n_lines - 1)
        obs.append(
            StepObservations(
                pivot_id="pivot",
                index=j,
                midpoint=np.array([u, 0.0]),
                heading=0.0,
                drive_ids=tuple(ids[d] for d in drv),
                drive_s_m=s,
                lateral_m=lat,
                types=types[li],
                cluster=label,
            )
        )
    return obs, truth
