"""Training infrastructure shared by the learned denoisers (RAE, and later NTASD and AFN).

``models``: which models the config trains and with what settings (config level, no torch: the
Snakefile imports it while parsing); ``spec``: ``ModelSpec``, one model's resolved settings (also
importable from ``models``); ``tasks``: how a method's settings become a training task;
``data``: training sequences cut and augmented from rendered clips (``SequenceDataset``);
``loop``: the generic trainer with exact resume, validation and curves (``Trainer``);
``job``: one training job of the workflow (rule train_denoiser).

Import the submodules directly; this package file stays empty of imports so that reading the
config does not load torch.
"""
