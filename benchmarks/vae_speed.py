"""How fast V trains and encodes on this machine.

Prints training throughput at the `fast` preset's batch size, encoding throughput batched and one
image at a time, and, as the reference measured in the same run, the machine's float32 matrix
product rate, with V's achieved FLOP rate as a fraction of it. ``--full`` also times a whole
`fast` V training run (synthesis, training, classifier) in a temporary folder.

    .venv/bin/python benchmarks/vae_speed.py [--full] [--threads N]
"""

from __future__ import annotations

import argparse
import tempfile
import time

import torch
from torch.utils.flop_counter import FlopCounterMode

from imagine.config import vision_preset
from imagine.models.vision import ConvVAE


def rate(fn, repeats: int = 3) -> float:
    fn()  # warm up
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return 1.0 / best


def flops(fn) -> int:
    with FlopCounterMode(display=False) as counter:
        fn()
    return counter.get_total_flops()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="also time a whole fast V training")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = vision_preset("fast")

    n = 2048
    a, b = torch.randn(n, n), torch.randn(n, n)
    peak = 2 * n**3 * rate(lambda: a @ b)

    torch.manual_seed(0)
    vae = ConvVAE(config.latent_dim).to(memory_format=torch.channels_last)
    optimizer = torch.optim.Adam(vae.parameters(), lr=config.lr)
    x = torch.rand(config.batch_size, 3, 64, 64).contiguous(memory_format=torch.channels_last)

    def train_step():
        loss = vae.loss(x, config.beta)
        optimizer.zero_grad()
        loss.total.backward()
        optimizer.step()

    train_flops = flops(train_step)
    train_rate = rate(train_step)

    vae.eval()
    batch = torch.rand(1000, 3, 64, 64).contiguous(memory_format=torch.channels_last)
    one = batch[:1]
    with torch.no_grad():
        encode_flops = flops(lambda: vae.encode(batch))
        batched = rate(lambda: vae.encode(batch))
        single = rate(lambda: [vae.encode(one) for _ in range(100)])

    def line(label: str, images_per_s: float, flop_rate: float | None = None) -> None:
        text = f"{label:34s}{images_per_s:10.0f} images/s"
        if flop_rate is not None:
            text += f"  ({flop_rate / 1e9:.1f} GFLOP/s, {flop_rate / peak:.2f} of peak)"
        print(text)

    print(f"threads: {args.threads}")
    print(f"{'reference: float32 matmul':34s}{peak / 1e9:10.1f} GFLOP/s")
    line(f"V training, batch {config.batch_size}:", train_rate * config.batch_size,
         train_rate * train_flops)  # fmt: skip
    line("V encoding, batch 1000:", 1000 * batched, batched * encode_flops)
    line("V encoding, one at a time:", 100 * single)
    if args.full:
        start = time.perf_counter()
        from imagine.models.vision_training import train_vae

        with tempfile.TemporaryDirectory() as folder:
            train_vae(config, folder)
        print(f"fast V training, whole run:      {time.perf_counter() - start:10.0f} s")


if __name__ == "__main__":
    main()
