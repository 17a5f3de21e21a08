"""The two rows of pits of a hysteresis cycle (hysteresis.py) found again in a rescan: which
detection is which punch (issue 37: an asymmetric loop moves the rows' ends by more than a
pit spacing, and another experiment's rows cross the lane).

- `imaged_rows`: each rescan's detections, less another experiment's (`without_known`), split
  into the descending and the ascending row, each placed along its drives
  (`monotone_placements` with smooth spacing) jointly so the two close at the loop's tips and
  their midline passes the middle (`placed_rows`).
- `rescan_disagreements`: pits the rescans place differently beyond their smooth difference.
"""

from __future__ import annotations

import numpy as np

from afm_core.localization.calibration.experiment import rescan
from afm_core.localization.calibration.matching import monotone_placements
from afm_core.localization.calibration.pits import DetectedPit, find_pits

# The two rows share the loop's tips (the descending sweep starts and the ascending one ends at
# the top of the cycle, they meet at its bottom): a placement of the rows one pit off moves a
# tip by a whole pit spacing, a right one leaves them apart by creep, coupling, noise and the
# local extrapolation where a tip pit is missing (tens to hundreds of nm). Half a spacing is
# where a closure is nearer a slipped placement than a right one, so beyond it the rows cannot
# be matched and the experiment says so.
TIP_CLOSURE_LIMIT = 0.5  # of the pit spacing at the tip
# Two rescans of the same row agree to a smooth difference (the compensated branches') and the
# pit-position noise; a pit matched differently in the two is a whole spacing off that. Beyond
# half a spacing the pit is left out (nearer a slip than an agreement).
RESCAN_AGREEMENT_LIMIT = 0.5  # of the pit spacing


class RowsNotMatched(RuntimeError):
    """The rows of pits could not be matched in a rescan (hysteresis_rows.placed_rows); the
    detections of the rescans so far are attached (`detected`), so a repeat elsewhere can
    ignore them."""

    def __init__(self, message: str, detected=()):
        super().__init__(message)
        self.detected = list(detected)


def imaged_rows(
    instrument, axis: int, box, pixel, rescans, branches, drives, ignore
) -> tuple[np.ndarray, list]:
    """The pits' positions along the cycled axis in each rescan of `box` (rows: rescans,
    columns: pits, NaN where not found) and each rescan's detections (less the `ignore`d).
    The two rows are placed together (`placed_rows`): they must share the loop's tips."""
    other = 1 - axis
    measured = np.full((len(rescans), len(branches)), np.nan)
    all_detected = []
    for row, direction in enumerate(rescans):
        scan = rescan(
            instrument, box[0], box[1], pixel, slow_axis=axis, slow_up=(direction == "up")
        )
        detected = find_pits(scan)
        if len(detected) < 8:
            raise RuntimeError(
                f"hysteresis ({'xy'[axis]}): only {len(detected)} pits found in the {direction} "
                "rescan"
            )
        if ignore is not None and len(ignore):
            # another image put them there: up to ~1 um off along this rescan's slow axis (the
            # compensation residual of a full-range pass), well within 0.3 um across it
            known = np.asarray(ignore, float).reshape(-1, 2)
            detected = without_known(detected, known, axis)
        all_detected.append([[p.x, p.y] for p in detected])
        along = np.array([[p.x, p.y][axis] for p in detected])
        across = np.array([[p.x, p.y][other] for p in detected])
        keep, offset = _split_rows(along, across)
        rows = {}
        for branch, sign in (("descending", -1.0), ("ascending", 1.0)):
            in_row = np.flatnonzero(keep & (np.sign(offset) == sign))
            rows[branch] = (np.flatnonzero(branches == branch), along[in_row])
        try:
            placed = placed_rows(rows, drives, axis, direction)
        except RuntimeError as exc:
            raise RowsNotMatched(str(exc), [p for d in all_detected for p in d]) from exc
        for wanted, positions in placed.values():
            measured[row, wanted] = positions
    return measured, all_detected


def placed_rows(rows: dict, drives: np.ndarray, axis: int, direction: str) -> dict:
    """{branch: (pit indices, position per pit or NaN)}: the placement of each row's
    detections along its drives (`monotone_placements`) chosen jointly so that the rows close
    at the loop's tips (the descending row's first pit and the ascending row's last one are
    both at the top of the cycle, the other two at its bottom). Where the loop is asymmetric
    the tips land microns from their drive value, more than a pit spacing, so the drive alone
    cannot say which pit an end detection is; the shared tips can, whatever the loop's shape.
    RuntimeError when no placement closes within TIP_CLOSURE_LIMIT of the spacing."""
    options = {}
    for branch, (wanted, positions) in rows.items():
        placements = monotone_placements(drives[wanted], positions, smooth_spacing=True)
        if not placements:
            raise RuntimeError(
                f"hysteresis ({'xy'[axis]}): only {len(positions)} pits of the {branch} row found "
                f"in the {direction} rescan"
            )
        options[branch] = [
            (misfit, np.where(index >= 0, positions[np.maximum(index, 0)], np.nan))
            for misfit, index in placements
        ]
    top, bottom = float(drives.max()), float(drives.min())
    middle = 0.5 * (top + bottom)
    wanted_d, wanted_a = rows["descending"][0], rows["ascending"][0]
    best = None
    for misfit_d, pos_d in options["descending"]:
        tips_d, spacing_d = _row_tips(drives[wanted_d], pos_d, (top, bottom, middle))
        for misfit_a, pos_a in options["ascending"]:
            tips_a, spacing_a = _row_tips(drives[wanted_a], pos_a, (top, bottom, middle))
            closure = np.abs(tips_d[:2] - tips_a[:2])
            # the absolute anchor where the tips are outside the box (both rows one pit off
            # still close there, the branches converge): the loop's midline at the middle
            # drive is the middle, to the compensation residual (~1 um) against a spacing
            # of several um there
            midline = 0.5 * (tips_d[2] + tips_a[2]) - middle
            score = float(np.sum(closure**2)) + midline**2 + misfit_d + misfit_a
            if best is None or score < best[0]:
                best = (score, closure, np.minimum(spacing_d, spacing_a)[:2], pos_d, pos_a)
    _, closure, spacing, pos_d, pos_a = best
    if np.any(closure > TIP_CLOSURE_LIMIT * spacing):
        raise RuntimeError(
            f"hysteresis ({'xy'[axis]}): the rows of pits do not close at the loop's tips in the "
            f"{direction} rescan (top {closure[0] * 1e9:.0f} nm, bottom {closure[1] * 1e9:.0f} nm "
            f"apart; pit spacing {spacing.min() * 1e9:.0f} nm; {len(rows['descending'][1])} and "
            f"{len(rows['ascending'][1])} of {len(wanted_d)} pits per row found): cannot tell "
            "which pit is which; repeat the experiment (afm calibrate --only hysteresis_"
            f"{'xy'[axis]}), with a smaller cycle_fraction if the loop's tips fell outside the "
            "rescan (a wide, strongly asymmetric loop)"
        )
    return {"descending": (wanted_d, pos_d), "ascending": (wanted_a, pos_a)}


TIP_FIT_PITS = 4  # the pits nearest a tip that a local quadratic through them extrapolates


def _row_tips(drive: np.ndarray, position: np.ndarray, ends) -> tuple[np.ndarray, np.ndarray]:
    """Where a row puts the cycle's `ends` (top, bottom), and the pit spacing there (the
    change over one pit step): a quadratic in the drive through the TIP_FIT_PITS matched pits
    nearest each end (a line through fewer), which is the end pit itself where it was
    matched. Local, because near a reversal the branch bends more than a cubic over the whole
    row follows (a wide loop's tips)."""
    found = np.isfinite(position)
    x, y = drive[found], position[found]
    step = float(np.median(np.abs(np.diff(np.sort(drive)))))
    tips, spacings = [], []
    for end in ends:
        near = np.argsort(np.abs(x - end))[:TIP_FIT_PITS]
        coefficients = np.polyfit(x[near], y[near], 2 if near.size >= 3 else 1)
        inward = end - np.sign(end - x.mean()) * step
        tip = float(np.polyval(coefficients, end))
        tips.append(tip)
        spacings.append(abs(tip - float(np.polyval(coefficients, inward))))
    return np.array(tips), np.array(spacings)


def rescan_disagreements(measured: np.ndarray, branches: np.ndarray) -> np.ndarray:
    """Pits whose positions in the rescans differ by more than RESCAN_AGREEMENT_LIMIT of the
    row's median pit spacing (matched to different pits): left out of the fit."""
    disagree = np.zeros(measured.shape[1], dtype=bool)
    if measured.shape[0] < 2:
        return disagree
    for branch in np.unique(branches):
        columns = np.flatnonzero(branches == branch)
        rows = measured[:, columns]
        both = np.all(np.isfinite(rows), axis=0)  # a pit missing in a rescan is not used anyway
        if both.sum() < 2:
            continue
        mean = rows[:, both].mean(axis=0)
        spacing = float(np.median(np.abs(np.diff(mean))))
        # the rescans differ smoothly by the compensated branches' difference (model error x
        # loop width, ~2 um on a loop of 0.18): a line in the position, fitted on the pits
        # that follow it; a pit matched one off differs from it by a spacing
        difference = rows[0, both] - rows[-1, both]
        inliers = np.ones(difference.size, dtype=bool)
        for _ in range(3):
            trend = np.polyfit(mean[inliers], difference[inliers], 1 if inliers.sum() > 2 else 0)
            off = np.abs(difference - np.polyval(trend, mean))
            inliers = off <= RESCAN_AGREEMENT_LIMIT * spacing
            if inliers.sum() < 2:
                break
        disagree[columns[both]] = off > RESCAN_AGREEMENT_LIMIT * spacing
    return disagree


# A pit belongs to a row when it lies within ROW_SPREAD robust scales (median absolute
# distance, ~0.67 sigma: ROW_SPREAD 5 is ~3.4 sigma, a 0.07 % false-rejection rate for
# Gaussian wander) of the row's line and nearer it than half the gap to the other row.
ROW_SPREAD = 5.0


def _split_rows(along: np.ndarray, across: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two rows of pits (descending, ascending) as two lines across-vs-along: they wander
    by the moves' random error (~0.1 um over a cycle), and on a wide loop they are neither
    parallel nor far apart (issue 37: loop 0.25, coupling 0.05: 0.55 um apart at one end,
    0.15 um at the other, where the branch gap's small move after a reversal hardly moves
    the scanner), so one middle line lost a row's end. Started from the least-squares line,
    each pit goes to the nearer row line and each line is refitted on its own pits; pits far
    off both (another experiment's) are left out (keep False). offset < 0: the descending
    row; its size is the distance to the row's own line."""
    # the least-squares line through all pits passes between the rows (as many pits each);
    # a robust middle line locked onto one row when the rows converge (issue 37, loop 0.25)
    keep = np.ones(len(along), dtype=bool)
    offset = across - np.polyval(np.polyfit(along, across, 1), along)
    side = np.sign(offset)
    for _ in range(5):
        members = [keep & (side == sign) for sign in (-1.0, 1.0)]
        if min(m.sum() for m in members) < 3:
            break
        lines = [np.polyfit(along[m], across[m], 1) for m in members]
        distance = np.stack([across - np.polyval(line, along) for line in lines])
        nearer = np.argmin(np.abs(distance), axis=0)
        side = np.where(nearer == 0, -1.0, 1.0)
        own = np.abs(distance[nearer, np.arange(len(along))])
        gap = np.abs(distance[0] - distance[1])
        scale = np.median(own[keep])
        keep = (own < ROW_SPREAD * scale) & (own < 0.5 * gap)
    return keep, side * np.maximum(np.abs(offset), 1e-15)


# Another image placed a known pit up to ~1.5 um differently in each axis (the compensation
# residual of a full-range pass against that of a short fast-axis stroke, up to ~10 % of half
# a loop width of 0.25 of the range); within this reach a detection may be one of them.
KNOWN_SEARCH = 3.0e-6  # m
# Once the common shift is known, a detection this close to a shifted known pit is it: pits
# land to ~50 nm, the shift varies by a few tens of nm over the few um the known pits span.
KNOWN_GATE = 0.4e-6  # m


def without_known(
    detected: list[DetectedPit], known: np.ndarray, slow_axis: int
) -> list[DetectedPit]:
    """`detected` less the `known` pits (another experiment's, imaged elsewhere). The other
    image placed them all by about the same shift (microns, issue 37: 1.0 um along y for the x
    cycle's rows crossing the y lane): among the offsets from known pits to detections within
    KNOWN_SEARCH, the one that brings the most known pits within KNOWN_GATE of a detection
    is that shift (a pit of this experiment nearby agrees with at most one known pit), and
    every detection within KNOWN_GATE of a shifted known pit goes."""
    if not detected or not len(known):
        return detected
    points = np.array([[p.x, p.y] for p in detected])
    delta = points[None, :, :] - known[:, None, :]
    near = np.all(np.abs(delta) < KNOWN_SEARCH, axis=2)
    if not near.any():
        return detected
    relevant = known[near.any(axis=1)]
    best, best_votes = None, 0
    for shift in delta[near]:
        distance = np.linalg.norm(points[None, :, :] - (relevant + shift)[:, None, :], axis=2)
        votes = int(np.sum(distance.min(axis=1) < KNOWN_GATE))
        if votes > best_votes or (
            votes == best_votes and np.linalg.norm(shift) < np.linalg.norm(best)
        ):
            best, best_votes = shift, votes
    distance = np.linalg.norm(points[None, :, :] - (relevant + best)[:, None, :], axis=2)
    drop = np.any(distance < KNOWN_GATE, axis=0)
    return [p for j, p in enumerate(detected) if not drop[j]]
