"""Isik et al. 2021's temporal ablations, each against the paper's definition (Sec. 3.3, 3.5, 5.5.4, 5.5.5), and
the discarded history where a reprojection fails (Sec. 4.1). Behaviour is probed on a small untrained network
over two frames with zero motion, not read back from the flags.

Paper definitions (switch: what the full model does):
* Eq. 3 -- the pixel embeddings are accumulated with lambda;  * Eq. 5 -- the noisy radiance is accumulated;
* temporal kernel (Eq. 7-8) -- the last kernel also filters the warped previous output;
* learned lambda -- lambda is predicted per pixel (ours-heur: the constant 0.8);
* U-Net history input -- the warped accumulated embedding (ours-wpred: the warped previous prediction).
"""
from __future__ import annotations

import dataclasses

import pytest
import torch

from denoisers.nets.afn import AFNConfig, AFNNet
from denoisers.nets.afn_task import frame_step, sample_features
from denoisers.reproductions.isik2021 import VARIANTS
from tests.test_afn import BUFFERS, SMALL, _batch

torch.set_num_threads(1)

#: variant -> (Eq. 3, Eq. 5, temporal kernel, learned lambda, U-Net history input), from the paper's text.
PAPER = {
    "ours": (True, True, True, True, "embedding"),
    "ours-heur": (True, True, True, False, "embedding"),        # Sec. 5.5.4: constant lambda = 0.8
    "ours-wpred": (False, False, True, True, "prediction"),     # Sec. 5.5.4: both accumulations off, kernel kept
    "ours-ntk": (True, True, False, True, "embedding"),         # Sec. 5.5.5: no temporal kernel
    "ours-nar": (True, False, True, True, "embedding"),         # Sec. 5.5.5: no radiance accumulation
}


def variant_config(name: str) -> AFNConfig:
    flags = {key: value for key, value in VARIANTS[name].items() if key not in ("affinity_dim",)}
    return AFNConfig(**{**SMALL, **flags})


def run(model: AFNNet, valid: float = 1.0, perturb_history_output: float = 0.0):
    """Two frames with zero motion; returns (step at t=0, step at t=1)."""
    batch = _batch(n=1, length=2)
    steps, history = [], None
    with torch.no_grad():
        for t in range(2):
            samples = {b: batch[b][:, t] for b in BUFFERS}
            if history is not None and perturb_history_output:
                history = dataclasses.replace(history, output=history.output * perturb_history_output)
            step = frame_step(model, sample_features(samples, batch["world_to_view"][:, t]), samples["radiance"].mean(1),
                              batch["motion"][:, t], batch["valid"][:, t] * valid, history, backend="torch")
            steps.append(step)
            history = step.history
    return steps


@pytest.mark.parametrize("name", sorted(PAPER))
def test_temporal_variant_switches_follow_the_paper(name: str) -> None:
    eq3, eq5, temporal_kernel, learned_lambda, history_input = PAPER[name]
    torch.manual_seed(0)
    model = AFNNet(variant_config(name)).eval()
    first, second = run(model)
    current_embedding = model.embed(sample_features({b: _batch(n=1, length=2)[b][:, 1] for b in BUFFERS},
                                                    _batch(n=1, length=2)["world_to_view"][:, 1])).float()
    with torch.no_grad():
        accumulated = not torch.allclose(second.history.embedding, current_embedding, atol=1e-6)
    assert accumulated == eq3
    noisy = _batch(n=1, length=2)["radiance"][:, 1].mean(1)
    radiance_accumulated = second.history.radiance is not None and not torch.allclose(second.history.radiance, noisy)
    assert radiance_accumulated == eq5
    # The temporal kernel reads the previous output: scaling it changes this frame's output only with the kernel.
    torch.manual_seed(0)
    scaled = run(AFNNet(variant_config(name)).eval(), perturb_history_output=3.0)[1]
    assert (not torch.allclose(scaled.output, second.output)) == (temporal_kernel or history_input == "prediction")
    if learned_lambda:
        assert float(second.blend.std()) > 0
    else:
        assert bool((second.blend == 0.8).all())
    assert model.config.history_input == history_input


def test_ntk_output_ignores_the_previous_output_but_wpred_reads_it_through_the_unet() -> None:
    """Separates the two ways the previous output can matter (the probe above accepts either for wpred)."""
    for name, reads in (("ours-ntk", False), ("ours-wpred", True)):
        torch.manual_seed(0)
        base = run(AFNNet(variant_config(name)).eval())[1]
        torch.manual_seed(0)
        scaled = run(AFNNet(variant_config(name)).eval(), perturb_history_output=3.0)[1]
        assert (not torch.allclose(scaled.output, base.output)) == reads, name


def test_a_failed_reprojection_discards_the_history() -> None:
    """Sec. 4.1: with every pixel's reprojection invalid, the second frame is denoised exactly as a first frame
    (no accumulation, no temporal taps, no history in the U-Net input)."""
    torch.manual_seed(0)
    model = AFNNet(AFNConfig(**SMALL)).eval()
    _, invalid = run(model, valid=0.0)
    batch = _batch(n=1, length=2)
    samples = {b: batch[b][:, 1] for b in BUFFERS}
    with torch.no_grad():
        fresh = frame_step(model, sample_features(samples, batch["world_to_view"][:, 1]), samples["radiance"].mean(1),
                           batch["motion"][:, 1], batch["valid"][:, 1] * 0.0, None, backend="torch")
    assert torch.allclose(invalid.output, fresh.output, atol=1e-6)
    assert bool((invalid.blend == 0).all())
    assert torch.allclose(invalid.history.radiance, samples["radiance"].mean(1), atol=1e-6)
