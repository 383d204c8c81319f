"""Problems beyond the robot (SPEC 17): a state-space model, its simulator, filters written for
any dimension, and the scoring of the noise estimate itself.

A scenario picks its problem with `problem:`; the robot (every other part of the package) stays
the default and keeps its own pipeline. Layout:

- `base`: the `Problem` interface (dimensions, f/F/G, h/H, angle-valued measurement components,
  the simulator, which state components are scored as position);
- `linear`: a linear time-invariant system, by default the survey's (Dunik et al. 2017);
- `schema`: the scenario file of a problem (`problem: linear`), validated strictly;
- `kalman`: the generic (E)KF step and its likelihood, shared by every filter;
- `filters`: the dimension-generic filters (kinds of the registry: ekf, ekf-oracle, sage-husa,
  als, ekf-ml, vb-r) and `als_identify`, the autocovariance least squares;
- `scoring`: per-run and per-filter tables of the state and the noise estimate;
- `experiment`: a problem scenario end to end (runs, tables, manifest) and `report_section`.
"""
