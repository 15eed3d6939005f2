"""Inference speed of the Isik et al. 2021 rows (issue 13 §3): AFN (full, single-frame, K1) and KPCN ms/frame
at 128^2 and 256^2 through the registry methods (what the evaluation times), the networks' convolution
GFLOP/s as a fraction of a float32 sgemm timed in the same interleaved rounds (target >= 30 %), the affinity
kernels' share of a frame (one 13 x 13 kernel, native and torch), and the peak resident memory.

    python benchmarks/afn_speed.py [--sizes 128 256] [--width 0.5] [--threads 1] [--repeats 9]

Items are timed round-robin (every item once per round, median over rounds), so a load change on this
shared machine hits all of them alike. Untrained networks: speed does not depend on the weights. GFLOP per
frame counts every convolution and matrix product (the per-sample embedding's 1 x 1 layers at S samples, the
U-Net, KPCN's convolutions) with torch's FlopCounterMode, 2 FLOPs per multiply-add; kernel application is not
counted.
"""
from __future__ import annotations

import argparse
import os
import resource

import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from denoisers import affinity, registry
from denoisers.methods import afn as _afn, kpcn as _kpcn  # noqa: F401 -- registers the methods
from denoisers.nets.afn import AFNConfig, AFNNet
from denoisers.nets.kpcn import KPCNConfig, KPCNNet
from denoisers.registry import Frame
from rae_speed import TARGET_FRACTION, Item, gemm_items, load_average, print_network_table, time_rounds

BUFFERS = {"radiance": 3, "diffuse": 3, "specular": 3, "normal": 3, "depth": 1, "roughness": 1, "albedo": 3,
           "flags": 4}
VARIANTS = {"afn": {}, "afn single": {"temporal": False}, "afn K1 17x17": {"temporal": False, "kernels": 1,
                                                                           "dilate": False, "kernel_size": 17}}


def frames(size: int, count: int, spp: int) -> list[Frame]:
    """``count`` synthetic frames of size x size with ``spp`` samples of every buffer, static camera."""
    generator = torch.Generator().manual_seed(size)
    return [Frame(samples={b: torch.rand(spp, c, size, size, generator=generator) for b, c in BUFFERS.items()},
                  pixel={"motion": torch.zeros(2, size, size), "valid": torch.ones(1, size, size)}, index=index,
                  meta={"camera": {"to_world": torch.eye(4).tolist()}}) for index in range(count)]


#: The ops counted as network arithmetic: convolutions and the matrix products of AFN's per-sample embedding
#: (its 1 x 1 layers run as F.linear). Kernel application (native, or torch einsum / bmm) is left out.
NETWORK_OPS = ("convolution", "mm", "addmm")


def conv_flops(model: nn.Module, method, frame: Frame) -> int:
    """FLOPs (2 per multiply-add) of the network's convolutions and matrix products in one denoise() call."""
    counter = FlopCounterMode(display=False)
    with torch.no_grad(), counter:
        method.denoise(frame)
    method.reset()
    counts = counter.get_flop_counts().get("Global", {})
    return int(sum(count for op, count in counts.items() if op.__name__.split(".")[0] in NETWORK_OPS))


def build_items(sizes: list[int], width: float, kpcn_width: float, spp: int, count: int, gemm_size: int) -> list[Item]:
    items: list[Item] = []
    for size in sizes:
        stream = frames(size, count, spp)
        nets = {name: (AFNNet(AFNConfig(width=width, **net)), "afn") for name, net in VARIANTS.items()}
        nets["kpcn"] = (KPCNNet(KPCNConfig(width=kpcn_width)), "kpcn")
        for name, (model, registered) in nets.items():
            torch.manual_seed(0)
            method = registry.get(registered).from_model(model.eval())
            flops = conv_flops(model, method, stream[0])

            def run(index: int, method=method, stream=stream) -> None:
                method.denoise(stream[index % len(stream)])

            items.append(Item(f"{name} denoise()", size, width if registered == "afn" else kpcn_width, run,
                              flops=flops))
        image, features = torch.rand(1, 3, size, size), torch.rand(1, 8, size, size)
        a, c = torch.rand(1, 1, size, size), torch.rand(1, 1, size, size)
        for backend in ("native", "torch"):
            if backend == "native" and _native_missing():
                continue
            items.append(Item(f"affinity 13x13 {backend}", size, None,
                              lambda _, b=backend, i=image, f=features, a=a, c=c:
                              affinity.affinity_sums(i, f, a, c, 13, 1, backend=b)))
    return items + gemm_items(gemm_size)


def _native_missing() -> bool:
    from denoisers import native

    return native.load_affinity() is None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--width", type=float, default=0.5, help="AFN U-Net width (config/isik2021.yaml: 0.5)")
    parser.add_argument("--kpcn-width", type=float, default=0.25, help="KPCN width (25 features of Bako's 100)")
    parser.add_argument("--spp", type=int, default=4, help="samples per pixel fed to the methods")
    parser.add_argument("--threads", type=int, default=1, help="torch threads; 1 is what the evaluation uses")
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--gemm-size", type=int, default=1024)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} thread(s), {args.spp} spp, AFN width {args.width:g}, KPCN width "
          f"{args.kpcn_width:g}; median of {args.repeats} interleaved rounds after {args.warmup}; load average "
          f"{load_average()} on {os.cpu_count()} CPUs")
    items = build_items(args.sizes, args.width, args.kpcn_width, args.spp, args.warmup + args.repeats,
                        args.gemm_size)
    with torch.no_grad():
        medians = time_rounds(items, args.repeats, args.warmup)
    fractions, verdict = print_network_table(items, medians, args.gemm_size)
    print(f"  networks reach {min(fractions):.0%}-{max(fractions):.0%} of the sgemm rate (target >= "
          f"{TARGET_FRACTION:.0%}: {verdict}, kernel application excluded); peak resident memory "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB; load average {load_average()}")


if __name__ == "__main__":
    main()
