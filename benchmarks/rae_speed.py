"""Inference speed of the recurrent denoising autoencoder (RAE, Chaitanya et al. 2017) beside OIDN, and the
network's achieved GFLOP/s as a fraction of a float32 matrix multiply (sgemm) timed in the same run.

One process, the synthetic clip of ``benchmarks/denoiser_speed.py`` (plus a camera looking straight at it,
which the RAE needs for view-space normals), an untrained RAE per ``--widths`` entry (speed does not depend
on the weights). Per thread count, every item below runs once per round, rounds interleaved, so a change in
machine load hits all of them alike; the RAE streams the clip with its recurrent state carried:

* ``rae denoise()``: the evaluation method on a whole frame (sample means, input encoding, the network's
  inference path, decoding), as the evaluation calls it;
* ``net inference_step``: the bare network on prepared inputs (``RecurrentAutoencoder.inference_step``,
  channels-last with leaky ReLU fused into oneDNN's convolution, weights channels-last as the method
  keeps them);
* ``net step (plain)``: the plain eager ``step`` under ``torch.inference_mode`` with default-layout
  weights (what the method ran before);
* ``oidn denoise()``: OIDN (quality high, same thread count);
* sgemm of ``--gemm-size``^3 float32 through torch's two CPU backends: ``torch.mm`` (MKL) and the oneDNN
  matmul (``mkldnn_linear``, the library that also runs the convolutions). The faster one is taken as
  the CPU's practical limit (on the project's AMD EPYC machine MKL's reaches less than half of oneDNN's).

Medians over ``--repeats`` rounds after ``--warmup`` rounds: ms/frame, Mpix/s, OIDN's time / the time,
achieved GFLOP/s = ``conv_flops`` (convolutions only) / time, and that as a fraction of the sgemm rate.
Then ``torch.profiler`` over ``--profile-frames`` inference steps per size and width, with the sgemm
timed between them (medians over the frames): convolution time and GFLOP/s per resolution level, the
other operators, and one line per case saying where the time beyond "all convolutions at the sgemm
rate" goes, written from those numbers.

Usage: python benchmarks/rae_speed.py [--sizes 128 256] [--widths 1.0 0.5] [--threads 1 [2]] [--spp 2]
           [--repeats 9] [--warmup 2] [--gemm-size 1024] [--profile-frames 7]
"""
from __future__ import annotations

import argparse
import copy
import math
import os
import statistics
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile

from denoisers import registry
from denoisers.methods.rae import RecurrentAutoencoderDenoiser
from denoisers.nets.rae import RAEConfig, RecurrentAutoencoder, State, conv_flops, fused_conv_available
from denoisers.nets.rae_task import INPUT_BUFFERS, prepare_inputs
from denoisers.nets.view import world_to_view
from denoisers.registry import Frame
from scenegen.camera import look_at_matrix

try:
    from benchmarks.denoiser_speed import only_declared, synthetic_frames
except ImportError:  # run as a script: benchmarks/ is on sys.path, the repository root may not be
    from denoiser_speed import only_declared, synthetic_frames

#: Camera 3 m in front of the synthetic clip looking at it: its world normals (+z towards the viewer) are
#: then view-space normals unchanged.
CAMERA_TO_WORLD = look_at_matrix(np.array([0.0, 0.0, 3.0]), np.zeros(3), np.array([0.0, 1.0, 0.0])).tolist()
TARGET_FRACTION = 0.30          # issue: at least 30 % of the sgemm rate
#: Operators of a convolution call (self times add up) and the one per call whose shapes give its FLOPs:
#: the fused oneDNN op on the fast path, aten::conv2d when it falls back to the plain convolution.
CONV_OPS = ("mkldnn::_convolution_pointwise", "aten::conv2d", "aten::convolution", "aten::_convolution",
            "aten::mkldnn_convolution", "aten::_slow_conv2d_forward", "aten::thnn_conv2d")
CONV_FLOP_OPS = ("mkldnn::_convolution_pointwise", "aten::conv2d")


@dataclass
class Item:
    """One timed thing: a label, its size and width (None for OIDN / sgemm), and a call per round."""

    label: str
    size: int | None
    width: float | None
    run: Callable[[int], None]
    flops: int = 0


def rae_frames(size: int, spp: int, count: int) -> list[Frame]:
    """The synthetic clip restricted to the buffers of the sample-feature RAE (``rae_samples``: the same network
    as ``rae``, which reads its features from the G-buffer instead), with the camera it needs."""
    info = RecurrentAutoencoderDenoiser.info
    frames = []
    for frame in synthetic_frames(size, spp, count):
        restricted = only_declared(frame, info)
        restricted.meta = {"camera": {"to_world": CAMERA_TO_WORLD}}
        frames.append(restricted)
    return frames


def prepared(model: RecurrentAutoencoder, frame: Frame) -> torch.Tensor:
    """(1, in_channels, H, W) network input of a frame, as the method prepares it."""
    means = {buffer: frame.mean(buffer) for buffer in INPUT_BUFFERS}
    x, _ = prepare_inputs(model.config, means["radiance"], means["albedo"], means["normal"], means["depth"],
                          means["roughness"], world_to_view(frame.meta["camera"]["to_world"]))
    return x[None]


def stream(step: Callable[[torch.Tensor, State | None], tuple[torch.Tensor, State]],
           inputs: list[torch.Tensor]) -> Callable[[int], None]:
    """A per-round call running ``step`` on frame ``round`` with the state of the previous round."""
    state: list[State | None] = [None]

    def run(index: int) -> None:
        _, state[0] = step(inputs[index], state[0])
    return run


def plain_step(model: RecurrentAutoencoder) -> Callable[[torch.Tensor, State | None], tuple[torch.Tensor, State]]:
    """The eager ``step`` under inference mode: the method's network call before the inference path."""
    def run(x: torch.Tensor, state: State | None) -> tuple[torch.Tensor, State]:
        with torch.inference_mode():
            return model.step(x, state)
    return run


def gemm_items(n: int) -> list[Item]:
    """sgemm n x n x n float32 through torch.mm (MKL) and, if available, the oneDNN matmul."""
    generator = torch.Generator().manual_seed(0)
    a, b = torch.randn(n, n, generator=generator), torch.randn(n, n, generator=generator)
    items = [Item("sgemm torch.mm (MKL)", None, None, lambda _: torch.mm(a, b), flops=2 * n**3)]
    try:
        a_dnnl = a.to_mkldnn()
        torch._C._nn.mkldnn_linear(a_dnnl, b, None)  # a @ b.T: the same FLOPs
        items.append(Item("sgemm oneDNN (mkldnn_linear)", None, None,
                          lambda _: torch._C._nn.mkldnn_linear(a_dnnl, b, None), flops=2 * n**3))
    except (AttributeError, RuntimeError) as error:
        print(f"(oneDNN sgemm unavailable: {error})")
    return items


def build_items(sizes: list[int], widths: list[float], spp: int, frames: int, gemm_size: int) -> list[Item]:
    """Every timed item: per size the RAE paths per width and OIDN, then the sgemms."""
    items: list[Item] = []
    for size in sizes:
        for width in widths:
            config = RAEConfig(width=width)
            torch.manual_seed(0)
            model = RecurrentAutoencoder(config).eval()
            plain = copy.deepcopy(model)                                # default layout, as before
            method = RecurrentAutoencoderDenoiser.from_model(model)     # model's weights now channels-last
            method.reset()
            clip = rae_frames(size, spp, frames)
            inputs = [prepared(model, frame) for frame in clip]
            flops = conv_flops(config, size, size)
            items.append(Item("rae denoise()", size, width, lambda i, m=method, c=clip: m.denoise(c[i]), flops))
            items.append(Item("net inference_step", size, width, stream(model.inference_step, inputs), flops))
            items.append(Item("net step (plain)", size, width, stream(plain_step(plain), inputs), flops))
        oidn = registry.build("oidn")
        oidn.reset()
        clip = [only_declared(frame, oidn.info) for frame in synthetic_frames(size, spp, frames)]
        items.append(Item("oidn denoise()", size, None, lambda i, m=oidn, c=clip: m.denoise(c[i])))
    return items + gemm_items(gemm_size)


def time_rounds(items: list[Item], repeats: int, warmup: int) -> list[float]:
    """Median seconds per call of every item, all items once per round."""
    seconds: list[list[float]] = [[] for _ in items]
    for index in range(warmup + repeats):
        for item, record in zip(items, seconds):
            start = time.perf_counter()
            item.run(index)
            elapsed = time.perf_counter() - start
            if index >= warmup:
                record.append(elapsed)
    return [statistics.median(record) for record in seconds]


# ------------------------------------------------------------------------------------------- profile
@dataclass
class Layer:
    """Convolutions of one input/weight shape in the profiled step (per frame)."""

    level: int
    c_in: int
    c_out: int
    pixels: str
    calls: int
    seconds: float
    flops: int


@dataclass
class Profile:
    """Where the inference step's time goes per frame (torch.profiler self times)."""

    total: float                                  # seconds, all operators
    layers: list[Layer]                           # the convolutions, by shape
    other: dict[str, float]                       # non-convolution operator -> seconds
    limit: float                                  # GFLOP/s of the faster sgemm, timed between the frames

    @property
    def conv(self) -> float:
        return sum(layer.seconds for layer in self.layers)


def profile_step(width: float, size: int, spp: int, frames: int, gemm: list[Item]) -> Profile:
    """Profile ``frames`` inference steps (after two unprofiled ones) of the network at width and size, one
    profiler run per frame with the ``gemm`` items timed after each; every operator's and layer's time and
    the sgemm rate are medians over the frames (robust to a load spike during one of them)."""
    torch.manual_seed(0)
    model = RecurrentAutoencoderDenoiser.from_model(RecurrentAutoencoder(RAEConfig(width=width))).model
    inputs = [prepared(model, frame) for frame in rae_frames(size, spp, frames + 2)]
    state = None
    for x in inputs[:2]:
        _, state = model.inference_step(x, state)
    layer_times: dict[tuple, list[float]] = defaultdict(list)
    other_times: dict[str, list[float]] = defaultdict(list)
    layers: dict[tuple, Layer] = {}
    gemm_seconds: list[list[float]] = [[] for _ in gemm]
    for x in inputs[2:]:
        with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
            _, state = model.inference_step(x, state)
        for item, record in zip(gemm, gemm_seconds):
            start = time.perf_counter()
            item.run(0)
            record.append(time.perf_counter() - start)
        this_frame: dict[tuple, float] = defaultdict(float)
        this_other: dict[str, float] = defaultdict(float)
        for event in prof.key_averages(group_by_input_shape=True):
            seconds = event.self_cpu_time_total * 1e-6
            shapes = event.input_shapes
            if event.key not in CONV_OPS or len(shapes) < 2 or len(shapes[0]) != 4 or len(shapes[1]) != 4:
                name = event.key.replace("aten::", "")
                this_other[name if event.key not in CONV_OPS else "convolution (shape unknown)"] += seconds
                continue
            (n, c_in, h, w), (c_out, _, kh, kw) = shapes[0], shapes[1]
            key = (n, c_in, h, w, c_out, kh, kw)
            layer = layers.setdefault(key, Layer(round(math.log2(size / h)), c_in, c_out, f"{h}x{w}", 0, 0.0, 0))
            this_frame[key] += seconds
            if event.key in CONV_FLOP_OPS:  # 3 x 3 "same" convolutions, stride 1: output h x w
                layer.calls = event.count
                layer.flops = 2 * n * h * w * c_in * c_out * kh * kw * event.count
        for key, seconds in this_frame.items():
            layer_times[key].append(seconds)
        for name, seconds in this_other.items():
            other_times[name].append(seconds)
    for key, layer in layers.items():
        layer.seconds = statistics.median(layer_times[key])
    other = {name: statistics.median(times + [0.0] * (frames - len(times))) for name, times in other_times.items()}
    other = {name: t for name, t in other.items() if t > 0}
    total = sum(layer.seconds for layer in layers.values()) + sum(other.values())
    limit = max(item.flops / statistics.median(record) / 1e9 for item, record in zip(gemm, gemm_seconds))
    return Profile(total, sorted(layers.values(), key=lambda layer: (layer.level, -layer.flops)), other, limit)


def explain(prof: Profile, size: int, width: float) -> str:
    """One line on what keeps the rate below the sgemm rate, from the profile's numbers: the time each part
    takes beyond what its FLOPs would take at the sgemm rate."""
    limit = prof.limit
    flops = sum(layer.flops for layer in prof.layers)
    ideal = flops / (limit * 1e9)
    conv_loss = prof.conv - ideal
    other_time = sum(prof.other.values())
    worst = max(prof.layers, key=lambda layer: layer.seconds - layer.flops / (limit * 1e9))
    worst_loss = worst.seconds - worst.flops / (limit * 1e9)
    top = ", ".join(f"{name} {t * 1e3:.2f}" for name, t in sorted(prof.other.items(), key=lambda kv: -kv[1])[:3])
    conv_rate = flops / prof.conv / 1e9
    if conv_loss > 0:
        in_convs = (f"{conv_loss * 1e3:.1f} ms ({conv_loss / prof.total:.0%}) in convolutions running at "
                    f"{conv_rate:.0f} GFLOP/s (largest: {worst.c_in}->{worst.c_out} ch at {worst.pixels} px, "
                    f"{worst.flops / worst.seconds / 1e9:.0f} GFLOP/s, {worst_loss * 1e3:.2f} ms of it)")
    else:  # within the noise of the sgemm timed alongside
        in_convs = f"none in convolutions as a whole ({conv_rate:.0f} GFLOP/s)"
    return (f"w{width:g} {size}x{size}: {prof.total * 1e3:.1f} ms profiled, of which {ideal * 1e3:.1f} ms would be "
            f"the convolutions at the sgemm rate ({limit:.0f} GFLOP/s); lost: {in_convs}, {other_time * 1e3:.1f} ms "
            f"({other_time / prof.total:.0%}) in operators without FLOPs (ms: {top})")


# ---------------------------------------------------------------------------------------------- main
def print_timings(items: list[Item], medians: list[float], args: argparse.Namespace) -> None:
    """The side-by-side table of the interleaved rounds."""
    timed = {(item.label, item.size, item.width): (item, t) for item, t in zip(items, medians)}
    rates = {item.label: item.flops / t / 1e9 for item, t in zip(items, medians) if item.label.startswith("sgemm")}
    limit = max(rates.values())
    print(f"sgemm {args.gemm_size}^3 float32, same rounds: "
          + ", ".join(f"{label} {rate:.1f} GFLOP/s" for label, rate in rates.items())
          + f"  -> limit taken: {limit:.1f} GFLOP/s")
    print(f"  {'size':8s} {'width':>5s}  {'path':20s} {'ms/frame':>9s} {'Mpix/s':>7s} {'OIDN t/t':>9s} "
          f"{'GFLOP/frame':>11s} {'GFLOP/s':>8s} {'of sgemm':>9s}")
    paths = ("rae denoise()", "net inference_step", "net step (plain)")
    for size in args.sizes:
        oidn_time = timed[("oidn denoise()", size, None)][1]
        rows = [(label, width) for width in args.widths for label in paths] + [("oidn denoise()", None)]
        for label, width in rows:
            item, seconds = timed[(label, size, width)]
            rate = item.flops / seconds / 1e9 if item.flops else None
            flops = f"{item.flops / 1e9:11.2f}" if item.flops else f"{'-':>11s}"
            rate_text = f"{rate:8.1f} {rate / limit:9.1%}" if rate else f"{'-':>8s} {'-':>9s}"
            print(f"  {f'{size}x{size}':8s} {width if width is not None else '-':>5}  {label:20s} "
                  f"{seconds * 1e3:9.2f} {size * size / seconds / 1e6:7.3f} {oidn_time / seconds:9.2f} "
                  f"{flops} {rate_text}")
    fast = {(s, w): timed[("net inference_step", s, w)] for s in args.sizes for w in args.widths}
    fractions = [item.flops / t / 1e9 / limit for item, t in fast.values()]
    verdict = "met" if min(fractions) >= TARGET_FRACTION else "NOT met"
    print(f"  net inference_step reaches {min(fractions):.0%}-{max(fractions):.0%} of the sgemm rate "
          f"(target >= {TARGET_FRACTION:.0%}: {verdict}); speed-up over the plain step: "
          + ", ".join(f"{s}/w{w:g} {timed[('net step (plain)', s, w)][1] / fast[(s, w)][1]:.2f}x"
                      for s in args.sizes for w in args.widths))


def print_profiles(gemm: list[Item], unprofiled: dict[tuple[int, float], float], args: argparse.Namespace) -> None:
    """Per size and width: convolution time and rate by resolution level, the other operators, and the
    one-line explanations."""
    print(f"\nprofile of net inference_step (torch.profiler self times, median over {args.profile_frames} frames; "
          f"per-call profiler overhead included; '% of sgemm' against the sgemm timed between those frames):")
    print(f"  {'size':8s} {'width':>5s} {'level':>6s} {'px':>9s} {'out ch':>7s} {'ms':>7s} {'% time':>7s} "
          f"{'% FLOPs':>8s} {'GFLOP/s':>8s} {'of sgemm':>9s}")
    lines = []
    for size in args.sizes:
        for width in args.widths:
            prof = profile_step(width, size, args.spp, args.profile_frames, gemm)
            flops_total = sum(layer.flops for layer in prof.layers)
            for level in sorted({layer.level for layer in prof.layers}):
                group = [layer for layer in prof.layers if layer.level == level]
                seconds, flops = sum(g.seconds for g in group), sum(g.flops for g in group)
                channels = sorted({g.c_out for g in group})
                ch = f"{channels[0]}-{channels[-1]}" if len(channels) > 1 else str(channels[0])
                print(f"  {f'{size}x{size}':8s} {width:>5g} {f'1/{2**level}':>6s} {group[0].pixels:>9s} {ch:>7s} "
                      f"{seconds * 1e3:7.2f} {seconds / prof.total:7.1%} {flops / flops_total:8.1%} "
                      f"{flops / seconds / 1e9:8.1f} {flops / seconds / 1e9 / prof.limit:9.1%}")
            others = ", ".join(f"{name} {t * 1e3:.2f} ms" for name, t in
                               sorted(prof.other.items(), key=lambda kv: -kv[1])[:5])
            print(f"  {'':8s} {'':5s} not convolution: {others}; profiled total {prof.total * 1e3:.2f} ms "
                  f"(unprofiled median {unprofiled[(size, width)] * 1e3:.2f} ms); sgemm {prof.limit:.1f} GFLOP/s")
            lines.append(explain(prof, size, width))
    print("\nwhat limits GFLOP/s (from the profile above):")
    for line in lines:
        print("  " + line)


def report(threads: int, args: argparse.Namespace) -> None:
    """Timings, then profiles, at one thread count."""
    torch.set_num_threads(threads)
    print(f"\n=== {threads} thread(s); load average {load_average()} on {os.cpu_count()} CPUs at the start ===")
    items = build_items(args.sizes, args.widths, args.spp, args.warmup + args.repeats, args.gemm_size)
    with torch.no_grad():
        medians = time_rounds(items, args.repeats, args.warmup)
    print_timings(items, medians, args)
    unprofiled = {(item.size, item.width): t for item, t in zip(items, medians) if item.label == "net inference_step"}
    print_profiles([item for item in items if item.label.startswith("sgemm")], unprofiled, args)
    print(f"(load average {load_average()} at the end; above {os.cpu_count()} means threads waited for a core, "
          f"which disturbs multi-threaded timings most)")


def print_network_table(items: list[Item], medians: list[float], gemm_size: int) -> tuple[list[float], str]:
    """Print the same-run sgemm rate and one line per sized item (ms/frame, GFLOP/frame, GFLOP/s, fraction of
    the sgemm rate); return the networks' fractions and the verdict against TARGET_FRACTION."""
    limit = max(item.flops / t / 1e9 for item, t in zip(items, medians) if item.label.startswith("sgemm"))
    print(f"sgemm {gemm_size}^3 float32, same rounds: {limit:.1f} GFLOP/s (the faster backend)")
    print(f"  {'size':8s} {'path':26s} {'ms/frame':>9s} {'GFLOP/frame':>11s} {'GFLOP/s':>8s} {'of sgemm':>9s}")
    fractions = []
    for item, seconds in zip(items, medians):
        if item.size is None:
            continue
        rate = item.flops / seconds / 1e9 if item.flops else None
        if rate:
            fractions.append(rate / limit)
        text = f"{item.flops / 1e9:11.3f} {rate:8.1f} {rate / limit:9.1%}" if rate else f"{'-':>11s} {'-':>8s} {'-':>9s}"
        print(f"  {f'{item.size}x{item.size}':8s} {item.label:26s} {seconds * 1e3:9.2f} {text}")
    return fractions, "met" if fractions and min(fractions) >= TARGET_FRACTION else "NOT met"


def load_average() -> str:
    """The 1, 5 and 15 minute load averages."""
    return " / ".join(f"{value:.2f}" for value in os.getloadavg())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--widths", type=float, nargs="+", default=[1.0, 0.5],
                        help="RAE widths: 1.0 = the paper's network, 0.5 = the default config's")
    parser.add_argument("--threads", type=int, nargs="+", default=[1],
                        help="torch (and OIDN) threads; 1 is what the evaluation uses")
    parser.add_argument("--spp", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--gemm-size", type=int, default=1024)
    parser.add_argument("--profile-frames", type=int, default=7)
    args = parser.parse_args()
    print(f"torch {torch.__version__}, oneDNN fused conv: {fused_conv_available()}, {args.spp} spp, median of "
          f"{args.repeats} rounds after {args.warmup} warm-up rounds, all items interleaved per round; "
          f"untrained networks (speed does not depend on the weights)")
    for threads in args.threads:
        report(threads, args)


if __name__ == "__main__":
    main()
