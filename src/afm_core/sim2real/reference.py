"""The reference at the recorded geometry, and the session the fits re-simulate.

The recorded positions are turned into the drift trajectory D(t) that puts the particles where
the recording saw them (drift_trajectory.py). The reference is the deterministic re-simulation
(drift wander, positioning noise and sensor noise off) with that drift, plus the mean
noise-induced bias of nonlinear features (from re-simulations with sensor noise). Shape features
(widths, heights) are then compared at the recorded geometry. Position features are linear in
the drift: replays with D shifted by 10 nm in x and in y give each feature's sensitivity J
(2-vector), and the position residual against the model's own mean drift D0 is
r = recorded - reference + J (D(t) - D0(t)): exactly what a replay with the mean drift would
give, without its lost lines (where the scanner map has the feature, it gives that change
exactly). `ReferenceSession.residual` re-simulates r with candidate terms at given values.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from afm_core.sim.config import SimConfig, merge
from afm_core.sim2real.candidates import Candidate, merge_overrides
from afm_core.sim2real.drift_trajectory import ScannerMap, drift_trajectory, nominal_drift
from afm_core.sim2real.exclusions import Exclusions, ordinary_exclusions
from afm_core.sim2real.feature_table import (
    NOISE_GROUPS,
    PUSH_GROUPS,
    SHAPE_GROUPS,
    by_key,
    make_table,
    values_at,
)
from afm_core.sim2real.features import (
    POSITION_GROUPS,
    FeatureExtractor,
    extract_features,
    raster_noise_statistics,
)
from afm_core.sim2real.features_absolute import LEVEL_GROUPS, UPDOWN_GROUP
from afm_core.sim2real.force_samples import collecting
from afm_core.sim2real.mismatch import (
    Agreement,
    agreement,
    cause_words,
    likely_scanner_causes,
)
from afm_core.sim2real.protocol import deterministic, replay
from afm_core.sim2real.sample_realization import sample_covariance

MIN_MATCHED_FRACTION = 0.7  # of the recorded features the reference simulation must reproduce
SHIFT = 10e-9  # m, drift shift of the sensitivity replays
# sizes along the sample, in the commanded coordinates the images and lines are drawn in: the
# scanner's local gain scales them (a feed-forward's loop-width error of 0.318 against the
# model's 0.1 narrowed three images' particles from 124-128 nm to 109-111 nm half-width, the
# recording's 110 nm), so a term that moves the tip changes them. A scan line's width stays at
# the recorded geometry: it is a chord at an offset across the line the walk decides, and with
# it re-simulated the protocol's feed-forward asymmetry error (0.2) was no longer fitted
LATERAL_SIZE_GROUPS = ("raster.half_width",)
# compared at the recorded geometry: what a term that only moves the tip leaves as it is (the
# heights and profiles of what it meets, the substrate's level)
AT_GEOMETRY_GROUPS = (
    *(g for g in SHAPE_GROUPS if g not in LATERAL_SIZE_GROUPS),
    *LEVEL_GROUPS,
    UPDOWN_GROUP,
)
REALIZATION_NOISE_SEED = 3000  # their first noise seed (the replicas' are 1000, 1001, ...)
# image shapes whose response to the pixel phase is a staircase: their noise is drawn with the
# walk on (`_walk_staircase_variance`), WALK_REPLICAS replays from WALK_NOISE_SEED
STAIRCASE_GROUPS = ("raster.height", "raster.half_width")
WALK_REPLICAS = 2
WALK_NOISE_SEED = 2000


class ConfigMismatchError(ValueError):
    """The configuration does not describe the recorded session (other sample, other area)."""


class NoFeaturesError(ValueError):
    """The recording has nothing the diagnosis can compare (no scan lines, rasters or pushes)."""


class ReferenceSession:
    """Everything the fits re-use: the recording, the reference, the drift trajectory, the
    scanner map, and re-simulation of a parameter set (made by `build_reference`). nominal:
    the deterministic reference's features; replicas: (K, N) features of the sensor-noise
    re-simulations (their mean offset from nominal is the reference's bias); J, J_shape,
    mapped, rounding_variance: `_sensitivities`; moves: (time, distance) of the reference
    replay's free moves."""

    def __init__(
        self,
        ops,
        config,
        keys,
        f_rec,
        anchors,
        drift,
        table,
        scanner_map,
        *,
        nominal,
        replicas,
        J,
        J_shape,
        mapped,
        rounding_variance,
        moves,
        noise_seeds=(),
    ):
        bias = np.nan_to_num(np.nanmean(replicas - nominal, axis=0))
        reference = nominal + bias
        self.nominal, self.replicas, self.moves = nominal, replicas, moves
        self.J_shape, self.rounding_variance = J_shape, rounding_variance
        self.ops, self.config, self.keys = ops, config, keys
        self.base = deterministic(config)
        self.noise_seeds = list(noise_seeds)
        self._noise_runs: dict = {}
        self.noise_reference: dict = {}  # the sensor-noise overrides the reference was made with
        self.f_rec, self.anchors, self.drift, self.J = f_rec, anchors, drift, J
        self.bias, self.reference, self.table = bias, reference, table
        self.map, self.mapped = scanner_map, mapped
        self.d_rec = drift.offset(table.time)
        self.d_nom = nominal_drift(config, table.time)
        self.geo_rec = np.where(mapped, scanner_map.predict_all(keys, self.d_rec), np.nan)
        self.geo_model = scanner_map.predict_all(keys, np.where(mapped[:, None], self.d_nom, 0.0))
        self.recorded = values_at(f_rec, keys)
        self.shape = np.isin(table.groups, SHAPE_GROUPS)
        # what a term that only moves the tip cannot change: the heights and profiles, and the
        # substrate's absolute level (a lateral term puts a line's edge on a particle's flank in
        # the re-simulation, at the recorded geometry it is not there; candidates.Candidate)
        self.at_geometry = np.isin(table.groups, AT_GEOMETRY_GROUPS)
        self.push = np.isin(table.groups, PUSH_GROUPS)
        self.noisy = np.isin(table.groups, NOISE_GROUPS)
        self.replays = 0
        self.exclusions = Exclusions()  # what build_reference left out of the recording
        # the shape features' covariance from the substrate's unknown surface (build_reference:
        # sample_realization.py); None: not drawn
        self.sample_cov = None
        self.set_reference(reference, bias, {})
        self.r_before = self.r  # against the nominal model (a fitted noise level changes self.r)

    def set_reference(
        self, reference: np.ndarray, bias: np.ndarray, noise_overrides: dict
    ) -> None:
        """Judge the fits against another reference (replicas with a fitted noise level); the
        noise statistics against their own replicas (`noise_features`)."""
        self.noise_reference = noise_overrides
        if self.noisy.any() and self.noise_seeds:
            statistics = self.noise_features(noise_overrides)
            reference = np.where(self.noisy & np.isfinite(statistics), statistics, reference)
        self.reference, self.bias = reference, bias
        self.r = self.recorded - reference + self.shift()

    def shift(self, extra: np.ndarray | None = None) -> np.ndarray:
        """What moving the drift from the recorded trajectory to the model's (plus `extra`,
        (N, 2)) changes: the scanner map where it has the feature, J (linear) elsewhere."""
        target = self.d_nom if extra is None else self.d_nom + extra
        linear = np.einsum("ij,ij->i", self.J, self.d_rec - target)
        if not self.mapped.any():
            return linear
        at_target = (
            self.geo_model
            if extra is None
            else self.map.predict_all(self.keys, np.where(self.mapped[:, None], target, 0.0))
        )
        exact = self.geo_rec - np.where(self.mapped, at_target, np.nan)
        return np.where(self.mapped, exact, linear)

    def mapped_change(self, config) -> np.ndarray:
        """How `config`'s scanner moves the mapped position features from the model's (at the
        model's drift; 0 elsewhere), from its scanner map: no imaging, no pixel rounding."""
        offsets = np.where(self.mapped[:, None], self.d_nom, 0.0)
        self.replays += 1
        moved = ScannerMap(self.ops, self.f_rec, config, self.anchors).predict_all(
            self.keys, offsets
        )
        return np.where(self.mapped, np.nan_to_num(moved - self.geo_model), 0.0)

    def features(self, config, imaging=True) -> np.ndarray:
        self.replays += 1
        rep = replay(self.ops, config, drift=self.drift, imaging=imaging)
        return values_at(by_key(extract_features(rep.operations, self.anchors)), self.keys)

    def noise_replicas(self, overrides: dict, rasters_only: bool = False) -> np.ndarray:
        """(K, N) features of the sensor-noise re-simulations with the noise replicas' seeds and
        `overrides` (so only what the overrides change differs between two calls with the same
        `rasters_only`; rasters_only: scan lines are not imaged, which is all the noise
        statistics need, at a third of the cost, with the model's positioning noise)."""
        memo = (repr(overrides), rasters_only)
        if memo not in self._noise_runs:
            config = merge(
                self._statistics_config()
                if rasters_only
                else deterministic(self.config, sensor_noise=True),
                overrides,
            )
            self._noise_runs[memo] = np.array(
                [self._noisy_run(config, seed, rasters_only) for seed in self.noise_seeds]
            )
        return self._noise_runs[memo]

    def _statistics_config(self) -> SimConfig:
        """The config the noise statistics are re-simulated with: the sensor noise and the
        positioning noise on. Each scan line's start jitters, and on a rough, tilted substrate
        that moves the line's mean height: without it the streaks' reference was 0.033 nm where
        the recording, with 1/f noise 40 times under the model's, showed 0.036, and a 1/f level
        of 0.077 nm was fitted for it. (The other features' replicas leave it out: their
        positioning walk is analytic.)"""
        return merge(
            deterministic(self.config, sensor_noise=True),
            {
                "scanner": {
                    "positioning_noise_enabled": self.config.scanner.positioning_noise_enabled
                }
            },
        )

    def _noisy_run(self, config, noise_seed: int, rasters_only: bool) -> np.ndarray:
        self.replays += 1
        rep = replay(
            self.ops,
            config,
            noise_seed=noise_seed,
            drift=self.drift,
            imaging="rasters" if rasters_only else True,
        )
        return values_at(by_key(extract_features(rep.operations, self.anchors)), self.keys)

    def realization_offsets(self, realizations: int, overrides: dict) -> np.ndarray:
        """(realizations, N): how far the noise statistics (at the noise level `overrides`) of
        other realizations of the substrate's roughness and of the noise (the sample's seed and
        the noise seed changed) lie from their replicas' mean. The recording's roughness and
        noise are its own realizations."""
        memo = ("realizations", repr(overrides), realizations)
        if memo not in self._noise_runs:
            config = merge(self._statistics_config(), overrides)
            mean = self.noise_features(overrides)
            offsets = [
                self._noisy_run(
                    merge(config, {"seed": int(config.seed) + 1 + k}),
                    REALIZATION_NOISE_SEED + k,
                    True,
                )
                - mean
                for k in range(realizations)
            ]
            self._noise_runs[memo] = np.where(self.noisy, np.nan_to_num(np.array(offsets)), 0.0)
        return self._noise_runs[memo]

    def noise_features(self, overrides: dict) -> np.ndarray:
        """Mean noise statistics of the raster-only `noise_replicas`."""
        return np.mean(self.noise_replicas(overrides, rasters_only=True), axis=0)  # (lines: NaN)

    def noise_features_along(self, cand: Candidate, levels) -> np.ndarray:
        """(len(levels), N): the noise statistics of `noise_features` (NaN on the other features)
        with the sensor-noise term `cand` at each level.
        The simulator adds that noise to the rasters in proportion to its level, from draws that
        do not depend on it, so each seed's rasters at any level are those at 0 plus level / u
        times their change at u (within 5e-14 m of a re-simulation's, the float32 images'
        rounding): two re-simulations per seed for any number of levels, not one per level."""
        memo = ("along", cand.name)
        if memo not in self._noise_runs:
            unit = max(float(cand.nominal(self.config)[0]), 1e-10)
            self._noise_runs[memo] = (
                unit,
                [
                    [
                        self._rasters(
                            merge(self._statistics_config(), cand.overrides(self.config, [level])),
                            seed,
                        )
                        for level in (0.0, unit)
                    ]
                    for seed in self.noise_seeds
                ],
            )
        unit, runs = self._noise_runs[memo]
        out = np.empty((len(levels), len(self.keys)))
        for i, level in enumerate(levels):
            out[i] = np.mean(
                [
                    self._noise_statistics_between(at_zero, at_unit, float(level) / unit)
                    for at_zero, at_unit in runs
                ],
                axis=0,
            )
        return out

    def _rasters(self, config, noise_seed: int) -> list:
        """The raster operations of a raster-only re-simulation."""
        self.replays += 1
        rep = replay(self.ops, config, noise_seed=noise_seed, drift=self.drift, imaging="rasters")
        return [op for op in rep.operations if op.kind == "raster" and op.data is not None]

    def _noise_statistics_between(
        self, at_zero: list, at_unit: list, fraction: float
    ) -> np.ndarray:
        """(N,): the noise statistics of the rasters at_zero + fraction (at_unit - at_zero) (only
        the heights move; NaN on every other feature)."""
        features = []
        for zero, unit in zip(at_zero, at_unit):
            low, high = zero.data.height.astype(float), unit.data.height.astype(float)
            height = (low + fraction * (high - low)).astype(zero.data.height.dtype)
            features += raster_noise_statistics(
                dataclasses.replace(zero, data=dataclasses.replace(zero.data, height=height))
            )
        return values_at(by_key(features), self.keys)

    def drift_extra(self, terms) -> np.ndarray | None:
        """The drift offsets (N, 2) the drift terms at theta add to the model's."""
        extra = np.zeros((len(self.keys), 2))
        found = False
        t = self.table.time
        for (cand, theta0, _), part in terms:
            if cand.analytic == "drift_velocity":
                extra += (cand.clip(part) - theta0)[None, :] * t[:, None]
                found = True
            elif cand.analytic == "drift_ramp":
                extra += 0.5 * (cand.clip(part) - theta0)[None, :] * (t**2)[:, None]
                found = True
        return extra if found else None

    def residual(self, terms, theta) -> np.ndarray:
        """Residual (recorded - model) with the terms at theta, re-simulated where needed."""
        sizes = [t[0].size for t in terms]
        parts = np.split(np.asarray(theta, float), np.cumsum(sizes)[:-1])
        pairs = list(zip(terms, parts))
        simulated = [(t, p) for t, p in pairs if not t[0].analytic]
        drifts = [(t, p) for t, p in pairs if t[0].analytic in ("drift_velocity", "drift_ramp")]
        noises = [(t, p) for t, p in pairs if t[0].analytic == "sensor_noise"]
        linear = [
            (t, p)
            for t, p in pairs
            if t[0].analytic
            and t[0].analytic not in ("drift_velocity", "drift_ramp", "sensor_noise")
        ]
        extra = self.drift_extra(drifts)
        r = self.r.copy()
        if extra is not None:
            # drift: exactly through the scanner map (positions are where the drift puts them)
            r = self.recorded - self.reference + self.shift(extra)
            r = np.where(
                np.isfinite(r),
                r,
                self.r - sum(cols @ (cand.clip(p) - t0) for (cand, t0, cols), p in drifts),
            )
        if simulated:
            overrides = {}
            for (cand, _, _), part in simulated:
                overrides = merge_overrides(overrides, cand.overrides(self.config, part))
            imaging = any(c.imaging for (c, _, _), _ in simulated)
            sim = self.features(merge(self.base, overrides), imaging=imaging)
            resim = r + (self.reference - (sim + self.bias))
            keep = np.isfinite(resim) & ~self.noisy
            if not imaging:
                keep &= self.push
            if all(c.geometric for (c, _, _), _ in simulated):
                keep &= ~self.at_geometry
            # a feature the re-simulation loses (a line now missing its particle): its linear
            # prediction
            lin = r - sum(cols @ (p - theta0) for (_, theta0, cols), p in simulated)
            r = np.where(keep, resim, lin)
        for (cand, theta0, cols), part in linear:
            r = r - cols @ (cand.clip(part) - theta0)
        if noises:
            overrides = {}
            for (cand, _, _), part in noises:
                overrides = merge_overrides(overrides, cand.overrides(self.config, part))
            resim = r + self.noise_features(self.noise_reference) - self.noise_features(overrides)
            r = np.where(self.noisy & np.isfinite(resim), resim, r)
        return r


def build_reference(
    recorded_ops, config: SimConfig, sensor_replicas: int, say: Callable[[str], None]
) -> ReferenceSession:
    """The recording's features beside the reference re-simulation at its geometry: the drift
    trajectory (stages A and B), the reference and the check that the config describes the
    recording, the drift sensitivities and the sensor-noise replicas."""
    anchors = np.array([(s["x"], s["y"]) for s in config.sample.spheres], float).reshape(-1, 2)
    traces: dict = {}  # the force traces' sample-to-sample changes (signal_relations.py)
    heights: dict = {}  # the height samples and their times (height_spectrum.py)
    extractor, ops, f_rec = _read(collecting(recorded_ops, traces, heights), anchors)
    # what the re-simulation cannot reproduce (pushed particles' contact history) is left out
    # before anything is fitted to the recording, the drift trajectory first (exclusions.py)
    exclusions = ordinary_exclusions(ops, f_rec, config)
    f_rec = exclusions.apply(f_rec)
    if not f_rec:
        raise NoFeaturesError(
            "every feature of the recording is one the re-simulation cannot reproduce "
            f"({'; '.join(row['what'] for row in exclusions.rows)})"
        )
    base = deterministic(config)
    t_end = (
        max(op.start_time + (op.duration if np.isfinite(op.duration) else 0.0) for op in ops) + 1.0
    )

    say("drift trajectory of the recording")
    scanner_map = ScannerMap(ops, f_rec, config, anchors)
    drift = drift_trajectory(
        scanner_map.obs, config, t_end, scanner_map.moves, spans=scanner_map.spans
    )
    say("reference re-simulation at the recorded geometry")
    nominal = replay(ops, base, drift=drift)
    f_nom = by_key(extract_features(nominal.operations, anchors))
    # stage B: the imaged reference's own offsets corrected, once
    drift = drift_trajectory(
        scanner_map.refined(f_rec, f_nom),
        config,
        t_end,
        scanner_map.moves,
        spans=scanner_map.spans,
    )
    nominal = replay(ops, base, drift=drift)
    nominal_seen: dict = {}
    f_nom = by_key(extract_features(nominal.operations, anchors, nominal_seen))
    f_nom_kept = exclusions.apply(f_nom)
    _check_config_matches(
        agreement(extractor.particles_seen, nominal_seen, f_rec, f_nom_kept),
        {k[0] for k in f_rec if k not in f_nom and f_rec[k].group not in NOISE_GROUPS},
        {k[0] for k, f in f_nom_kept.items() if k not in f_rec and f.group not in NOISE_GROUPS},
        # only when the check fails: which scanner term would reproduce the recording
        explain=lambda nominal_score: cause_words(
            *likely_scanner_causes(
                ops,
                f_rec,
                extractor.particles_seen,
                config,
                anchors,
                t_end,
                nominal_score,
                MIN_MATCHED_FRACTION,
                say,
            )
        ),
    )
    matched = [k for k in f_rec if k in f_nom]
    say("drift sensitivities")
    shifted = []
    for axis in (0, 1):
        delta = np.zeros(2)
        delta[axis] = SHIFT
        shifted.append(
            by_key(
                extract_features(replay(ops, base, drift=drift.shifted(delta)).operations, anchors)
            )
        )
    say(f"noise replicas ({sensor_replicas} sensor-only)")
    sensor_cfg = deterministic(config, sensor_noise=True)
    reps_s = [
        by_key(
            extract_features(
                replay(ops, sensor_cfg, noise_seed=1000 + k, drift=drift).operations, anchors
            )
        )
        for k in range(sensor_replicas)
    ]
    keys = [k for k in matched if all(k in r for r in reps_s) and all(k in s for s in shifted)]

    table = make_table(keys, f_rec)
    nom = values_at(f_nom, keys)
    J, J_shape, mapped, rounding_variance = _sensitivities(table, nom, shifted, drift, scanner_map)
    rounding_variance = np.maximum(
        rounding_variance, _walk_staircase_variance(ops, config, drift, anchors, keys, table, nom)
    )
    sess = ReferenceSession(
        ops,
        config,
        keys,
        f_rec,
        anchors,
        drift,
        table,
        scanner_map,
        nominal=nom,
        replicas=np.array([values_at(r, keys) for r in reps_s]),
        J=J,
        J_shape=J_shape,
        mapped=mapped,
        rounding_variance=rounding_variance,
        moves=nominal.moves,
        noise_seeds=[1000 + k for k in range(sensor_replicas)],
    )
    say("other surfaces of the substrate")
    sess.sample_cov = sample_covariance(ops, config, drift, anchors, keys, table, nom)
    sess.exclusions = exclusions
    sess.force_differences = traces
    sess.height_samples = heights
    return sess


def _walk_staircase_variance(ops, config, drift, anchors, keys, table, nom) -> np.ndarray:
    """Per feature: the variance the positioning walk gives an image's particle height and
    half-width (0 on every other feature, and when the session has none).

    An image's half-width is the square root of a pixel count (extract_landmarks), a staircase
    in where the particle falls on the pixel grid; the walk before each image decides that to a
    few nm, and no derivative carries a staircase (the reference's geometry term is linear).
    So their noise is drawn: WALK_REPLICAS replays with the model's walk and sensor noise at the
    recorded drift, the mean squared departure from the reference pooled per group (two draws
    per feature are too few alone). Only images with pixels fine enough for shapes (PushProcedure's
    8 nm rescans) have these features; the protocol's images do not, and pay nothing."""
    staircase = np.isin(table.groups, STAIRCASE_GROUPS)
    out = np.zeros(len(keys))
    if not staircase.any():
        return out
    walking = merge(
        deterministic(config, sensor_noise=True),
        {"scanner": {"positioning_noise_enabled": config.scanner.positioning_noise_enabled}},
    )
    runs = np.array(
        [
            values_at(
                by_key(
                    extract_features(
                        replay(
                            ops, walking, noise_seed=WALK_NOISE_SEED + k, drift=drift
                        ).operations,
                        anchors,
                    )
                ),
                keys,
            )
            for k in range(WALK_REPLICAS)
        ]
    )
    departure = (runs - nom[None, :]) ** 2
    for group in STAIRCASE_GROUPS:
        sel = staircase & (table.groups == group)
        if sel.any() and np.isfinite(departure[:, sel]).any():
            out[sel] = float(np.nanmean(departure[:, sel]))
    return out


def _read(recorded_ops, anchors: np.ndarray):
    """(the feature extractor, the commands, the recorded features by key) in one pass over
    the recording: its measurements become features and are let go (a recording is never held
    whole); re-simulations need the commands only."""
    extractor, ops = FeatureExtractor(anchors), []
    for op in recorded_ops:
        extractor.add(op)
        ops.append(dataclasses.replace(op, data=None))
    if not ops:
        raise NoFeaturesError("the session holds no commands the simulator can re-run")
    f_rec = by_key(extractor.finish())
    if not f_rec:
        raise NoFeaturesError(f"no operation of the recording gave a feature: {_no_feature(ops)}")
    return extractor, ops, f_rec


def _no_feature(ops) -> str:
    """What the session holds and the likely cause, among the two the reader can tell apart:
    no measurement a feature comes from, or measurements that crossed no particle."""
    kinds: dict = {}
    for op in ops:
        kinds[op.kind] = kinds.get(op.kind, 0) + 1
    held = ", ".join(f"{n} {kind}" for kind, n in sorted(kinds.items()))
    measured = sum(kinds.get(k, 0) for k in ("scan_line", "raster", "push"))
    if not measured:
        return (
            f"its {len(ops)} commands ({held}) include no scan line, raster or push, the "
            "operations features come from; record scans or pushes over the particles"
        )
    return (
        f"its {measured} scan lines, rasters and pushes ({held}) crossed no particle: the "
        "scanned area is bare (the particles lie elsewhere on the sample) or the images are too "
        "coarse to resolve one"
    )


def _check_config_matches(agree: Agreement, lost_rec: set, lost_sim: set, explain=None):
    """ConfigMismatchError unless the reference at the recorded geometry shows the recording's
    particles and reproduces most of its features (`agree`: mismatch.agreement; lost_rec,
    lost_sim: operations with a feature of the sample only in the recording, only in the
    simulation). explain(the configuration's agreement score): the message's likely cause
    (mismatch.py: the scanner terms that would reproduce the recording), None: the sample."""
    # a drift trajectory can put the config's particles under the recorded lines one at a time
    # (one sphere fitted, by jumps of micrometres, to where six were seen), but not into the
    # images of them all: the images must show as many particles as the recording's
    if agree.seen_ratio < MIN_MATCHED_FRACTION:
        what = (
            f"the recording's {agree.images} images show {agree.seen_rec} particles, the "
            f"simulation of the same images with this config {agree.seen_sim} (each must be at "
            f"least {MIN_MATCHED_FRACTION:.0%} of the other)."
        )
    # whether the particles are where the config says (noise statistics are there on any sample)
    elif agree.feature_ratio < MIN_MATCHED_FRACTION:
        what = (
            f"of {agree.n_rec} recorded features of the sample only {agree.n_both} are "
            f"reproduced by the simulation ({agree.n_sim} simulated). Operations where the "
            f"recording saw a particle and the simulation did not: {sorted(lost_rec)[:10]}; the "
            f"reverse: {sorted(lost_sim)[:10]}."
        )
    else:
        return
    cause = (
        explain(agree.score)
        if explain is not None
        else " Check the sample (particle positions, seed) and the scanner area in the config."
    )
    raise ConfigMismatchError(f"the configuration does not match the recording: {what}{cause}")


def _sensitivities(table, nom: np.ndarray, shifted: list, drift, scanner_map: ScannerMap):
    """(J, J_shape, mapped, rounding_variance). J (N, 2): each feature's sensitivity to the
    drift offset, from the replays shifted by SHIFT (`shifted`: their features by key), the
    scanner map's where it has the feature (`mapped`), zero but for positions. J_shape: the
    shape features' sensitivity to the recorded geometry. rounding_variance: per feature, how
    far imaged positions depart from the map's straight response over the shifts."""
    keys = table.keys
    J = np.stack([(values_at(s, keys) - nom) / SHIFT for s in shifted], axis=1)
    J[np.abs(J) < 1e-3] = 0.0
    # positions: the scanner map's sensitivity (a replay's 10 nm shift also sees the pixel grid)
    d_rec = drift.offset(table.time)
    mapped = np.array([k in scanner_map.items for k in keys]) & np.isin(
        table.groups, POSITION_GROUPS
    )
    J_map = scanner_map.sensitivity(keys, d_rec)
    # how far the imaged positions depart from the scanner map's straight response over the
    # 10 nm shifts (the simulator renders coarse images on a fixed grid: a particle's centre
    # moves in small jumps): a geometry a few nm off the recorded one scrambles that much, so
    # it is noise, pooled per group
    J_rep = J.copy()
    expected = np.where(mapped[:, None], J_map, 0.0)
    rounding = mapped | (table.groups == "line.dir")
    nonlinear = np.zeros(len(keys))
    if rounding.any():
        dev2 = np.nansum(((J_rep - expected) * SHIFT) ** 2, axis=1) / 2
        for group in np.unique(table.groups[rounding]):
            sel = rounding & (table.groups == group)
            nonlinear[sel] = float(np.nanmean(dev2[sel]))
    J[mapped] = J_map[mapped]
    # features measured at the recorded geometry: their sensitivity to it (how far the
    # reference's geometry may be off enters their noise)
    J_shape = np.where(np.isin(table.groups, SHAPE_GROUPS + ("line.dir",))[:, None], J_rep, 0.0)
    # only positions move with the drift (a shape, a difference, a torsion: at the recorded
    # geometry; their replay "sensitivity" is rounding of the sampled profiles)
    J[~np.isin(table.groups, POSITION_GROUPS)] = 0.0
    return J, J_shape, mapped, nonlinear
