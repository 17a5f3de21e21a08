"""The localizer's calibration (book 7.2.2): the experiments that measure this instrument, and
the `Calibration` they produce.

Modules, one per experiment and what they share:
- model.py: the `Calibration` (what the experiments measured) and its YAML file;
- procedure.py: `run_calibration`, every experiment in order (or `only=` some of them, merged
  into an earlier file with `merge_calibration`), into one `Calibration`;
- fit_checks.py: `calibration_checks`, per fit its standard error, consistency between axes
  and experiments, and a warning naming the experiment to repeat;
- creep.py, hysteresis.py, scanner_matrix.py, motion_error.py, line_deflection.py,
  drift_statistics.py, map_errors.py: the experiments (`measure_*`) and their fits;
- experiment.py: the `Experiment` each returns, and the steps on the instrument they share
  (wait, punch a pit, rescan);
- pits.py: finding the punched pits in a rescan; matching.py: which pit is which punch;
  hysteresis_rows.py: the same for the two rows of a hysteresis cycle; hysteresis_cycle.py:
  the open-loop cycle that punches them;
- simulator_comparison.py: the results against a simulated instrument's configuration;
- figures.py: `calibration_figures`, a PNG of each experiment's raw data and fit from the
  report (what `afm calibrate --report` puts beside its readable summary).

Where the pits go. Every experiment records the tip's position by punching a pit (book
Fig. 7.6a, 7.7a, 7.12a) and finds the pits again in a rescan (pits.py).
A rescan is taken with the same scanner, so it measures positions in the image frame, which
is the frame the localizer's maps are in; its own distortion is kept small by scanning the
long direction of a pit pattern along the slow axis (one monotone pass, no fast-axis loop),
see each experiment. Sites are chosen on flat substrate away from the scanner centre (where
the default sample's particles are) and apart from each other; all are offsets from the
range centre and can be changed.

The image frame. Because the rescans use the scanner being calibrated, everything is
measured in the frame of the instrument's own images, which is the frame the localizer's
maps are in. What every image shares cannot be seen: the tube's x/y coupling and its
rotation against the sample (so the scanner matrix comes out near the identity and the
line deflection near 0 deg on the simulator, whatever is configured), and the small-move
gain of the compensated scanner, which sets a small image's scale on each axis and with it
the scale of the drift velocities measured in it. With the simulator's 10 % feed-forward
model error a short move after a reversal goes ~6 % farther than commanded: a drift
frame's slow axis (one monotone pass after a reversal) moves 1.059 x the commanded pixel,
its fast axis 1.040 x (the same +6 %, less the ~2 % of creep that cannot follow a line
oscillating at 0.75 Hz), so the drift velocities are ~6 % (y) and ~4 % (x) low against the
true ones (with the model error 0: scales 1.000 and 0.981, creep alone, so y exact and x
~2 % high). An image cannot see its own scale; the absolute scale and orientation need a
reference of known size and direction (a calibration grating) imaged like the frames it is
for (size, line rate, approach); the long full-range rescans of the hysteresis experiment
are on the scanner's long branches, whose compensated gain is within ~1 % of 1.
"""
