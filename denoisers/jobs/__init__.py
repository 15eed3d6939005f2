"""The evaluation's jobs: one module per workflow rule family, each reading renders and writing one output folder.

* :mod:`denoisers.jobs.denoise`: one row on one clip (rule ``denoise_clip``);
* :mod:`denoisers.jobs.scoring`: per-frame metrics of a denoised clip (``evaluate_clip``);
* :mod:`denoisers.jobs.robustness`: spikes and NaN/Inf injected into the samples (``robustness_clip``);
* :mod:`denoisers.jobs.stability`: the stability suite's rows and scores (``denoise_scenario``, ``score_scenario``);
* :mod:`denoisers.jobs.volumes`: the volumetric clips' rows (``denoise_volume``, ``evaluate_volume``);
* :mod:`denoisers.jobs.timing`: every row timed on the same frames (``time_methods``);
* :mod:`denoisers.jobs.tuning`: the hand-set baselines' grid search on training scenes (``tune_method``).

The building blocks they use (filters, kernels, metrics, losses, nets) stay in :mod:`denoisers`; a job imports
them, never the other way round.
"""
