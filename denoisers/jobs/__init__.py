"""The evaluation's jobs: the modules behind the workflow's rules, each reading renders and writing output folders.

* :mod:`denoisers.jobs.rows`: every clip of one row in one job (rules ``denoise_row``, ``evaluate_row``,
  ``robustness_row`` and their stability and volume counterparts ``*_scenario_row``, ``*_volume_row``), each clip
  by the modules below;
* :mod:`denoisers.jobs.denoise`: one row on one clip;
* :mod:`denoisers.jobs.scoring`: per-frame metrics of a denoised clip;
* :mod:`denoisers.jobs.robustness`: spikes and NaN/Inf injected into the samples;
* :mod:`denoisers.jobs.stability`: the stability suite's rows and the failure metrics of one clip;
* :mod:`denoisers.jobs.volumes`: the volumetric clips' rows;
* :mod:`denoisers.jobs.timing`: every row timed on the same frames (``time_methods``);
* :mod:`denoisers.jobs.tuning`: the hand-set baselines' grid search on training scenes (``tune_method``).

The building blocks they use (filters, kernels, metrics, losses, nets) stay in :mod:`denoisers`; a job imports
them, never the other way round.
"""
