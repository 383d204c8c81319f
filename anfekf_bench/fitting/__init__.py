"""Every fit of a filter's parameters before the batch, in one place (issue 33).

One entry point, `fit.fit_specs`: given (spec, training runs) pairs, it checks that the spec
declares a fit on that source (`FilterSpec.fit_sources`, filters/spec.py), reads each fit from the
run store's cache or computes it (`spec.fit(training)`), and returns the fitted values with their
fingerprint and manifest record. Each source supplies its training runs through one interface,
`fit.TrainingRuns`:

- "simulated" (`simulated.TrainingSet`): `training.runs` runs of the scenario's world, from seeds
  of a branch no evaluation run draws from; declared by ekf-ml and ekf-tuned (Nelder-Mead on the
  tuning kernel), kalmannet and ekf-aug-calibrated (ekf-aug's estimates at each run's end);
- "recorded" (`recorded.RecordedTraining`): a log's training segments, or a fold's drives of the
  other datasets; declared by a recorded scenario's ekf-tuned (grid search) and kalmannet;
- "own" (`own.OwnInnovations`): one recorded run's own innovations, never its truth; declared
  by ekf-ml.

How the fitted values reach the runs stays with the source: `fit_filters` (simulated) and
`fit_on_segments` / `fit_on_drives` (kalmannet) hand out `with_fit` copies of the specs;
`tune_segments` / `tune_drives` and `fit_on_own_innovations` return the noise records
real_experiment.recorded_run builds those filters from. The problems' likelihood fit
(problems/ml.py) is not here: it belongs to the problem interface.
"""
