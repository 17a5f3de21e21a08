"""The library of candidate physics: simulator config keys with a microscopist's name.

A candidate's parameters ARE config values (or a common factor on a list-valued key, such as
all creep fractions), so its fitted value is written straight into the updated simulator
configuration. Its design columns are the sensitivities of the features to those values,
computed by re-simulating with each value stepped. A candidate whose keys the configuration
does not have (an older simulator) is left out, and the report says so.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from afm_core.sim.config import SimConfig, merge


@dataclass
class Candidate:
    name: str  # short id
    words: str  # what a microscopist would call it
    keys: list  # dotted config keys, one per parameter
    steps: list  # finite-difference steps, in the parameters' units
    units: list  # for the report
    scale: bool = False  # the parameter is a factor on a list-valued key (nominal 1)
    enable: dict = field(
        default_factory=dict
    )  # dotted key -> value, set whenever the term is fitted
    lower: list | None = None  # bounds of the parameters (None: unbounded)
    upper: list | None = None
    display: list | None = None  # per parameter: (factor, unit) for the report
    # how the term acts, which decides how its design columns are computed:
    # geometric: it moves where the scanner puts the tip (drift, scanner); the heights and
    #   profiles of what is measured and the substrate's absolute level do not change at a
    #   given tip-particle geometry, and the diagnosis compares them at the recorded geometry,
    #   so its columns there are zero (a re-simulated loop-width error put two scan lines'
    #   edges on a particle's flank, their levels 18 and 63 sigma off, where the recording's
    #   were not: the held-out check of the true value got worse); sizes in commanded
    #   coordinates (widths) scale with the scanner's local gain and are re-simulated
    #   (reference.AT_GEOMETRY_GROUPS);
    # analytic: the columns follow in closed form from the reference ("drift_velocity",
    #   "drift_ramp": positions move by J t, J t^2 / 2; "height_gain": heights scale; "bow":
    #   the background curvature adds the curvature);
    # sensor_noise: it changes only the noise, so only noise statistics (line-offset and pixel
    #   noise) move; its columns and fits come from re-simulations with sensor noise on, with
    #   the noise replicas' seeds (only the noise level differs between them);
    # imaging=False: only force traces change (a replay without imaging suffices).
    geometric: bool = False
    analytic: str = ""
    imaging: bool = True
    # the term cannot act unless these config values hold (dotted key -> value), e.g. an
    # asymmetry of the hysteresis is inverted exactly by the controller's feed-forward
    requires: dict = field(default_factory=dict)
    # parameters chosen from the data by a search rather than fitted (a region's four edges):
    # they count in the evidence's complexity penalty like fitted ones
    searched: int = 0
    # a one-parameter term whose features bend within the plausible range (a feed-forward's
    # asymmetry error d scales positions by a_c^2 - a_s^2 with a_c = a_s - d, quadratic in d, plus
    # a curvature linear in d: the fit has two basins, d and about 2 a_s - d): the steps from the
    # nominal value searched whole, (lowest, highest); its column is the secant to the step that
    # fits the recording best (the choice counts as one searched parameter); None: the
    # derivative at the nominal value, by `steps`
    search_range: tuple | None = None

    @property
    def size(self) -> int:
        return len(self.keys)

    @property
    def complexity(self) -> int:
        return self.size + self.searched + (1 if self.search_range else 0)

    def nominal(self, config: SimConfig) -> np.ndarray:
        values = []
        for key in self.keys:
            if self.scale:
                values.append(1.0)
                continue
            value = get_key(config, key)
            enabled = all(get_key(config, k) == v for k, v in self.enable.items())
            values.append(float(value) if enabled or not self.enable else self.off_value(key))
        return np.array(values)

    def off_value(self, key: str) -> float:
        """The value meaning "absent" when the term's switch is off in the nominal config."""
        if key.endswith("static_friction_ratio"):
            return 1.0
        return 0.0

    def clip(self, theta) -> np.ndarray:
        theta = np.asarray(theta, float).copy()
        if self.lower is not None:
            theta = np.maximum(theta, self.lower)
        if self.upper is not None:
            theta = np.minimum(theta, self.upper)
        return theta

    def overrides(self, config: SimConfig, theta) -> dict:
        """Nested config overrides setting the parameters to theta."""
        theta = self.clip(theta)
        out: dict = {}
        active = True
        for key, value in zip(self.keys, theta):
            if self.scale:
                base = np.asarray(get_key(config, key), float)
                set_key(out, key, [float(v) for v in base * value])
            else:
                set_key(out, key, float(value))
                if key.endswith("static_friction_ratio") and value <= 1.0 + 1e-6:
                    active = False
                    set_key(out, key, 1.5)
        for key, value in self.enable.items():
            set_key(out, key, value if active else get_key(config, key))
        return out

    def apply(self, config: SimConfig, theta) -> SimConfig:
        return merge(config, self.overrides(config, theta))


@dataclass
class FrictionRegion(Candidate):
    """Tip-substrate friction scaled by one factor inside a rectangle of the sample (afm_task
    frame) found from the data (sim2real.regions); the factor is the parameter. Only the
    tip's friction is measured by the slides; the particles' substrate friction there is left
    as modelled."""

    bounds: tuple = (0.0, 0.0, 0.0, 0.0)

    @classmethod
    def at(cls, bounds, step: float = 0.3) -> FrictionRegion:
        x0, y0, x1, y1 = (float(b) for b in bounds)
        words = (
            "friction changes in one region of the sample: the tip-substrate friction differs "
            f"inside x {x0 * 1e6:.2f}-{x1 * 1e6:.2f} um, y {y0 * 1e6:.2f}-{y1 * 1e6:.2f} um "
            "(a patch of contamination or of another material)"
        )
        return cls(
            "friction_region",
            words,
            ["contact.friction_regions[-1].mu_tip_substrate_scale"],
            [float(step)],
            ["factor"],
            imaging=False,
            lower=[0.0],
            searched=4,
            bounds=(x0, y0, x1, y1),
        )

    def nominal(self, config: SimConfig) -> np.ndarray:
        return np.array([1.0])

    def overrides(self, config: SimConfig, theta) -> dict:
        x0, y0, x1, y1 = self.bounds
        region = {
            "x0": x0,
            "y0": y0,
            "x1": x1,
            "y1": y1,
            "substrate_friction_scale": 1.0,
            "mu_tip_substrate_scale": float(self.clip(theta)[0]),
        }
        return {
            "contact": {
                "friction_regions": [dict(r) for r in get_key(config, "contact.friction_regions")]
                + [region]
            }
        }


def get_key(config, key: str):
    node = config
    for part in key.split("."):
        node = node[part] if isinstance(node, dict) else getattr(node, part)
    return node


def has_key(config, key: str) -> bool:
    try:
        get_key(config, key)
        return True
    except (AttributeError, KeyError):
        return False


def set_key(tree: dict, key: str, value) -> None:
    parts = key.split(".")
    for part in parts[:-1]:
        tree = tree.setdefault(part, {})
    tree[parts[-1]] = value


def merge_overrides(a: dict, b: dict) -> dict:
    out = copy.deepcopy(a)
    for key, value in b.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge_overrides(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


NM = (1e9, "nm")
NM_S = (1e9, "nm/s")
# an asymmetry of 0.45 makes the loop 3.6 times steeper at one end of the range than at the
# other (slopes 1 -+ 2 a + 2 a^2): a feed-forward calibrated that far off is not concealed (the
# fit may still go beyond, within the bounds)
ASYMMETRY_SEARCH = (-0.45, 0.45)


# The library: one definition per candidate, grouped by the part of the instrument it describes;
# library() lists the groups in this order (the order `select` keeps and the report shows).

DRIFT = (
    Candidate(
        name="drift_velocity",
        words="thermal drift: the constant drift velocity differs from the model",
        keys=["drift.mean_velocity_x", "drift.mean_velocity_y"],
        steps=[5e-11, 5e-11],
        units=["m/s", "m/s"],
        display=[NM_S, NM_S],
        geometric=True,
        analytic="drift_velocity",
    ),
    Candidate(
        name="drift_ramp",
        words="drift ramp: the drift speeds up steadily (temperature still settling)",
        keys=["drift.acceleration_x", "drift.acceleration_y"],
        steps=[1e-13, 1e-13],
        units=["m/s^2", "m/s^2"],
        display=[(1e9, "nm/s^2"), (1e9, "nm/s^2")],
        geometric=True,
        analytic="drift_ramp",
    ),
)

CREEP = (
    Candidate(
        name="creep_amplitude",
        words="piezo creep: more (or less) creep after each move than modelled",
        keys=["scanner.creep_fractions"],
        steps=[0.5],
        units=["x nominal fractions"],
        scale=True,
        lower=[0.0],
        geometric=True,
        requires={"scanner.creep_enabled": True},
    ),
    Candidate(
        name="creep_time",
        words="piezo creep: the creep time constants differ (faster/slower settling)",
        keys=["scanner.creep_time_constants"],
        steps=[0.4],
        units=["x nominal time constants"],
        scale=True,
        lower=[0.05],
        geometric=True,
        requires={"scanner.creep_enabled": True},
    ),
)

HYSTERESIS = (
    Candidate(
        name="hysteresis_residual",
        words="hysteresis: the controller's feed-forward leaves more (or less) of the "
        "loop than modelled (its calibrated loop width is off)",
        keys=["controller.model_error"],
        steps=[0.05],
        units=["relative loop-width error"],
        lower=[-0.9],
        upper=[2.0],
        geometric=True,
        requires={
            "controller.hysteresis_compensation": True,
            "scanner.hysteresis_enabled": True,
        },
    ),
    Candidate(
        name="hysteresis_asymmetry",
        words="hysteresis: ascending and descending branches differ more (or less) "
        "than the controller's feed-forward assumes (its calibrated asymmetry is off)",
        keys=["controller.asymmetry_error"],
        steps=[0.03],
        units=[""],
        lower=[-0.8],
        upper=[0.8],
        geometric=True,
        search_range=ASYMMETRY_SEARCH,
        requires={
            "controller.hysteresis_compensation": True,
            "scanner.hysteresis_enabled": True,
        },
    ),
    Candidate(
        name="hysteresis_asymmetry_open_loop",
        words="hysteresis: ascending and descending branches differ "
        "(asymmetry, scanner driven open loop)",
        keys=["scanner.hysteresis_asymmetry"],
        steps=[0.05],
        units=[""],
        lower=[-0.8],
        upper=[0.8],
        geometric=True,
        search_range=ASYMMETRY_SEARCH,
        requires={
            "controller.hysteresis_compensation": False,
            "scanner.hysteresis_enabled": True,
        },
    ),
    Candidate(
        name="hysteresis_width",
        words="hysteresis: the loop is wider/narrower than calibrated",
        keys=["scanner.hysteresis_fraction"],
        steps=[0.01],
        units=["of range"],
        lower=[0.0],
        upper=[0.33],
        geometric=True,
        requires={"scanner.hysteresis_enabled": True},
    ),
)

SCANNER_GEOMETRY = (
    Candidate(
        name="coupling",
        words="x/y cross-coupling of the scanner tube",
        keys=["scanner.coupling_x_to_y", "scanner.coupling_y_to_x"],
        steps=[0.005, 0.005],
        units=["", ""],
        enable={"scanner.coupling_enabled": True},
        lower=[-0.5, -0.5],
        upper=[0.5, 0.5],
        geometric=True,
    ),
    Candidate(
        name="rotation",
        words="scan-line rotation (the scan axes are rotated)",
        keys=["scanner.deflection_deg"],
        steps=[0.3],
        units=["deg"],
        enable={"scanner.deflection_enabled": True},
        geometric=True,
    ),
    Candidate(
        name="bow",
        words="scanner bow (the image background is curved)",
        keys=["scanner.bow_curvature"],
        steps=[5.0],
        units=["1/m"],
        lower=[-300.0],
        upper=[300.0],
        analytic="bow",
    ),
)

TIP = (
    Candidate(
        name="tip_radius",
        words="tip radius: the tip is blunter/sharper than modelled",
        keys=["tip.apex_radius"],
        steps=[4e-9],
        units=["m"],
        lower=[1e-9],
        display=[NM],
    ),
    Candidate(
        name="tip_wear",
        words="tip wear: the tip blunts while sliding in contact",
        keys=["tip.wear_rate"],
        steps=[5e-4],
        units=["m per m slid"],
        enable={"tip.wear_enabled": True},
        lower=[0.0],
    ),
    Candidate(
        name="tip_asymmetry",
        words="tip asymmetry: one flank of the tip is blunter",
        keys=["tip.asymmetry"],
        steps=[0.15],
        units=[""],
        lower=[-0.9],
        upper=[0.9],
    ),
)

CONTACT = (
    Candidate(
        name="friction",
        words="tip-substrate friction coefficient differs",
        keys=["contact.mu_tip_substrate"],
        steps=[0.02],
        units=[""],
        lower=[0.0],
        imaging=False,
    ),
    Candidate(
        name="stick_slip",
        words="stick-slip: the tip sticks and slips while sliding",
        keys=["contact.static_friction_ratio"],
        steps=[0.3],
        units=["static/kinetic"],
        enable={"contact.stick_slip_enabled": True},
        lower=[1.0],
        imaging=False,
    ),
)

SENSOR = (
    Candidate(
        name="height_gain",
        words="z-sensor gain: heights are scaled (z calibration off)",
        keys=["noise.height_gain"],
        steps=[0.02],
        units=[""],
        lower=[0.1],
        upper=[10.0],
        analytic="height_gain",
    ),
    Candidate(
        name="white_noise",
        words="white z noise: the height signal is noisier (or quieter) from pixel to pixel "
        "than modelled (grainy images; a sample rougher at the pixel scale than modelled "
        "looks alike)",
        keys=["noise.height_white_sigma"],
        steps=[0.1e-9],
        units=["m"],
        lower=[0.0],
        display=[NM],
        analytic="sensor_noise",
    ),
    Candidate(
        name="coloured_noise",
        words="coloured (1/f) z noise: the height signal wanders more (or less) than "
        "modelled (whole scan lines offset from their neighbours: streaks in images)",
        keys=["noise.height_flicker_sigma"],
        steps=[0.1e-9],
        units=["m"],
        lower=[0.0],
        display=[NM],
        analytic="sensor_noise",
    ),
    Candidate(
        name="latency",
        words="sensor latency: signals lag the scan position",
        keys=["noise.sensor_latency"],
        steps=[3e-3],
        units=["s"],
        lower=[0.0],
        upper=[1.0],
        display=[(1e3, "ms")],
    ),
)


def library() -> list[Candidate]:
    """Every candidate term the tool knows (filtered by `available`). Copies: a candidate's
    lists and dicts are mutable, and a caller's change must not reach the next diagnosis."""
    return copy.deepcopy([*DRIFT, *CREEP, *HYSTERESIS, *SCANNER_GEOMETRY, *TIP, *CONTACT, *SENSOR])


def select(effects=None) -> list[Candidate]:
    """The library's candidates named in `effects` (names as in library(), e.g. "tip_radius"),
    in library order; None or empty: the whole library. A lab that suspects its tip diagnoses
    against the tip's terms only, in a fraction of the time (the others are not re-simulated)."""
    lib = library()
    if not effects:
        return lib
    names = [str(e).strip() for e in effects]
    known = {c.name for c in lib}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ValueError(
            f"effects: unknown {', '.join(repr(n) for n in unknown)}; the library has "
            + ", ".join(c.name for c in lib)
        )
    return [c for c in lib if c.name in names]


def available(config: SimConfig, candidates=None) -> tuple[list[Candidate], list[str]]:
    """(candidates whose keys this config has and that can act in it, notes on the others)."""
    candidates = library() if candidates is None else candidates
    ok, missing = [], []
    for candidate in candidates:
        keys = list(candidate.keys) + list(candidate.enable) + list(candidate.requires)
        if not all(has_key(config, key) for key in keys):
            missing.append(candidate.name)
        elif not all(get_key(config, key) == value for key, value in candidate.requires.items()):
            missing.append(
                f"{candidate.name} (cannot act unless "
                + ", ".join(f"{k} = {v}" for k, v in candidate.requires.items())
                + ")"
            )
        else:
            ok.append(candidate)
    return ok, missing
