"""The model store: trained models and part-way checkpoints committed beside the code, keyed by everything that
determines their weights (denoisers.store.keys), installed by the workflow instead of training
(denoisers.training.job), published and verified with ``python -m denoisers store`` (denoisers.store.cli)."""
from denoisers.store.entries import (Entry, ModelStore, StoreCollisionError, StoreError, file_digest,
                                     store_settings)
from denoisers.store.keys import checkpoint_key, model_key

__all__ = ["Entry", "ModelStore", "StoreCollisionError", "StoreError", "checkpoint_key", "file_digest", "model_key",
           "store_settings"]
