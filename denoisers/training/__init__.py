"""Training infrastructure shared by the learned denoisers (RAE, and later NTASD and AFN).

``data``: training sequences cut and augmented from rendered clips (``SequenceDataset``);
``loop``: the generic trainer with exact resume, validation and curves (``Trainer``).
"""
from __future__ import annotations

from denoisers.training.data import (Batch, SequenceConfig, SequenceDataset, SequencePlan, fixed_batches,
                                     load_training_clips)
from denoisers.training.loop import (CheckpointError, NonFiniteLossError, Trainer, TrainerConfig, TrainResult,
                                     load_checkpoint, load_model, lr_factor)

__all__ = ["Batch", "SequenceConfig", "SequenceDataset", "SequencePlan", "fixed_batches", "load_training_clips",
           "CheckpointError", "NonFiniteLossError", "Trainer", "TrainerConfig", "TrainResult", "load_checkpoint",
           "load_model", "lr_factor"]
