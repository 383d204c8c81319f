"""Problems beyond the robot (SPEC 17): a state-space model, its simulator, filters written for
any dimension, and the scoring of the noise estimate itself.

A scenario picks its problem with `problem:`; the robot (every other part of the package) stays
the default and keeps its own pipeline. Layout:

- `base`: the `Problem` interface (dimensions, f/F/G, h/H, angle-valued measurement components,
  the simulator, which state components are scored as position);
- `linear`: a linear time-invariant system, by default the survey's (Dunik et al. 2017);
- `module`: a user's own problem, a Python file the scenario names (`problem: module`);
- `schema`: the scenario file of a problem (`problem: linear`), validated strictly;
- `forms`: the kinds on these problems, read from the filter registry (each kind's spec names
  its form here, `problem_form`: no second list of kinds);
- `kalman`: the generic (E)KF step and its likelihood, shared by every filter;
- `filters`: the generic loop and the kinds ekf, ekf-oracle, sage-husa, vb-r (kinds of the
  registry, which says which problems each kind runs on); `als`: the autocovariance least
  squares (`als_identify`) and its filter; `ml`: the likelihood fit and its filter;
- `fast`: the fast engine, each family's loop compiled once by numba (the problem's functions
  passed as first-class functions of one signature);
- `scoring`: per-run and per-filter tables of the state and the noise estimate;
- `experiment`: a problem scenario end to end (training fits, runs, tables, manifest);
- `report`: its tables as text, for `anfekf run` and `anfekf report` (report.problems).
"""
