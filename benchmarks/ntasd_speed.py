"""Inference speed of the Hasselgren et al. 2020 variants (issue 12 §3): sampler + denoiser ms/frame at 128^2
and 256^2 through the registry method (what the evaluation times), the networks' convolution GFLOP/s as a
fraction of a float32 sgemm timed in the same interleaved rounds (target >= 30 %), and the kernel
application's share of a frame (the backend apply_kernels picks, native where it builds, beside the torch
reference).

    python benchmarks/ntasd_speed.py [--sizes 128 256] [--width 0.5] [--threads N] [--repeats 9]

Items are timed round-robin (every item once per round, median over rounds), so a load change on this
shared machine hits all of them alike. Untrained networks: speed does not depend on the weights.
GFLOP per frame counts the 3 x 3 convolutions of both U-Nets and the heads at the padded size (2 FLOPs per
multiply-add), from forward hooks; kernel application, warping, pooling and activations are not counted.
"""
from __future__ import annotations

import argparse
import os

import torch
from torch import nn

from denoisers import kernels, registry
from denoisers.methods import ntasd as _ntasd_methods  # noqa: F401 -- registers the variants
from denoisers.nets.ntasd import NTASDConfig, NTASDNet
from denoisers.registry import Frame
from denoisers.training.tasks import NTASD_VARIANTS
from rae_speed import TARGET_FRACTION, Item, gemm_items, load_average, print_network_table, time_rounds

LAYERS = 32
BUDGET = 4.0


def frames(size: int, count: int) -> list[Frame]:
    """``count`` synthetic frames of size x size with every stored layer, static camera."""
    generator = torch.Generator().manual_seed(size)
    out = []
    for index in range(count):
        normal = torch.zeros(3, size, size)
        normal[2] = 1.0
        out.append(Frame(samples={"radiance": torch.rand(LAYERS, 3, size, size, generator=generator),
                                  "albedo": torch.rand(1, 3, size, size, generator=generator)},
                         pixel={"motion": torch.zeros(2, size, size), "valid": torch.ones(1, size, size),
                                "gbuffer.normal": normal, "gbuffer.depth": torch.full((1, size, size), 2.0)},
                         index=index, meta={"camera": {"to_world": torch.eye(4).tolist()}}, budget=BUDGET))
    return out


def conv_flops(model: NTASDNet, frame: Frame) -> int:
    """FLOPs of every Conv2d in one denoise() of ``frame`` (forward hooks on the output shapes)."""
    total = 0

    def hook(module: nn.Conv2d, inputs: tuple, output: torch.Tensor) -> None:
        nonlocal total
        kh, kw = module.kernel_size
        total += 2 * module.in_channels * module.out_channels * kh * kw * output.shape[-2] * output.shape[-1]

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, nn.Conv2d)]
    method = registry.get(next(n for n, v in NTASD_VARIANTS.items()
                               if v == (model.config.variant, model.config.sampling))).from_model(model)
    with torch.no_grad():
        method.denoise(frame)
    for handle in handles:
        handle.remove()
    return total


def build_items(sizes: list[int], width: float, count: int, gemm_size: int) -> list[Item]:
    items: list[Item] = []
    for size in sizes:
        stream = frames(size, count)
        for name, (variant, sampling) in NTASD_VARIANTS.items():
            torch.manual_seed(0)
            model = NTASDNet(NTASDConfig(variant=variant, sampling=sampling, width=width)).eval()
            flops = conv_flops(model, stream[0])
            method = registry.get(name).from_model(model)

            def run(index: int, method=method, stream=stream) -> None:
                method.denoise(stream[index % len(stream)])

            items.append(Item(f"{name} denoise()", size, width, run, flops=flops))
        image = torch.rand(3, size, size)
        weights = torch.softmax(torch.rand(25, size, size), dim=0)
        items.append(Item("apply_kernels 5x5", size, None, lambda _, i=image, w=weights: kernels.apply_kernels(i, w)))
        # The torch reference beside the backend apply_kernels picks (the native one where it builds).
        items.append(Item("apply_kernels 5x5 (torch)", size, None,
                          lambda _, i=image, w=weights: kernels.apply_kernels_torch(i, w)))
    return items + gemm_items(gemm_size)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--width", type=float, default=0.5, help="U-Net width (0.5 = the default config's)")
    parser.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)),
                        help="torch threads (default: every core here, as the timing job behind the quality-versus-"
                             "speed chart runs with timing.threads null; the denoise jobs use evaluation.threads)")
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--gemm-size", type=int, default=1024)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} thread(s), budget {BUDGET:g} spp of {LAYERS} layers, width "
          f"{args.width:g}; median of {args.repeats} interleaved rounds after {args.warmup}; load average "
          f"{load_average()} on {os.cpu_count()} CPUs")
    items = build_items(args.sizes, args.width, args.warmup + args.repeats, args.gemm_size)
    with torch.no_grad():
        medians = time_rounds(items, args.repeats, args.warmup)
    fractions, verdict = print_network_table(items, medians, args.gemm_size)
    print(f"  networks reach {min(fractions):.0%}-{max(fractions):.0%} of the sgemm rate (target >= "
          f"{TARGET_FRACTION:.0%}: {verdict}); load average {load_average()} at the end")


if __name__ == "__main__":
    main()
