"""V's encoder in other float32 forms: is any faster than PyTorch's own convolutions? (issue 18)

An evaluation of 1000 greedy test episodes spends 80% of its time in V's four 4 x 4 stride-2
convolutions, and its target (under 1 s) asks for the same successes, so only float32 forms of
the same arithmetic are candidates. Times each form on the same batch of images, alternating
the forms ``--repeats`` times in one process (so a busy machine slows all of them alike), and
prints the best time per 1000 images and each form's largest difference from eager PyTorch:

- eager: ``ConvVAE.encoder`` on the input as evaluation hands it (``vision.to_input`` of uint8
  images (N, 64, 64, 3): channels-last strides, which oneDNN keeps from layer to layer);
- eager, NCHW: the same on a contiguous (N, 3, 64, 64) copy;
- torchscript: the encoder scripted, frozen and passed through ``optimize_for_inference``
  (oneDNN's blocked layout from the first layer to the last);
- space-to-depth: each 4 x 4 stride-2 convolution as a 2 x 2 stride-1 one on the
  pixel-unshuffled input (the same products and sums, in another order);
- unfold: each convolution as ``unfold`` and one matrix product.

    .venv/bin/python benchmarks/encoder_forms.py [--threads 2] [--images 1000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import time
import warnings
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F

from imagine.models.vision import ConvVAE, to_input


def convolutions(vae: ConvVAE) -> list[torch.nn.Conv2d]:
    return [m for m in vae.encoder if isinstance(m, torch.nn.Conv2d)]


def space_to_depth_weight(weight: torch.Tensor) -> torch.Tensor:
    """(O, C, 4, 4) -> (O, 4C, 2, 2): kernel offset (2 ky + dy, 2 kx + dx) of channel c becomes
    offset (ky, kx) of channel 4c + 2 dy + dx, pixel_unshuffle's channel order."""
    o, c = weight.shape[:2]
    return weight.reshape(o, c, 2, 2, 2, 2).permute(0, 1, 3, 5, 2, 4).reshape(o, 4 * c, 2, 2)


def space_to_depth_form(vae: ConvVAE) -> Callable[[torch.Tensor], torch.Tensor]:
    layers = [(space_to_depth_weight(m.weight.detach()).contiguous(), m.bias.detach())
              for m in convolutions(vae)]  # fmt: skip

    def encode(x: torch.Tensor) -> torch.Tensor:
        for weight, bias in layers:
            size = x.shape[-1] - x.shape[-1] % 2  # a stride-2 4 x 4 kernel never reads an odd edge
            x = F.conv2d(F.pixel_unshuffle(x[..., :size, :size], 2), weight, bias).relu_()
        return x.flatten(1)

    return encode


def unfold_form(vae: ConvVAE) -> Callable[[torch.Tensor], torch.Tensor]:
    layers = [(m.weight.detach().flatten(1), m.bias.detach()[:, None]) for m in convolutions(vae)]

    def encode(x: torch.Tensor) -> torch.Tensor:
        for weight, bias in layers:
            side = (x.shape[-1] - 4) // 2 + 1
            columns = F.unfold(x, 4, stride=2)  # (N, 16 C, side^2)
            x = (torch.matmul(weight, columns) + bias).reshape(len(x), -1, side, side).relu_()
        return x.flatten(1)

    return encode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--images", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    vae = ConvVAE().eval()
    generator = np.random.default_rng(0)
    images = to_input(generator.integers(0, 256, (args.images, 64, 64, 3), dtype=np.uint8))
    with warnings.catch_warnings():  # TorchScript is deprecated: measured, not used
        warnings.simplefilter("ignore", DeprecationWarning)
        frozen = torch.jit.freeze(torch.jit.script(vae.encoder))
        scripted = torch.jit.optimize_for_inference(frozen)
    forms = {
        "eager": vae.encoder,
        "eager, NCHW": lambda x: vae.encoder(x.contiguous()),
        "torchscript": scripted,
        "space-to-depth": space_to_depth_form(vae),
        "unfold": unfold_form(vae),
    }
    best = dict.fromkeys(forms, float("inf"))
    with torch.no_grad():
        reference = vae.encoder(images)
        differences = {n: (f(images) - reference).abs().max().item() for n, f in forms.items()}
        for _ in range(args.repeats):
            for name, form in forms.items():
                start = time.perf_counter()
                form(images)
                best[name] = min(best[name], time.perf_counter() - start)
    scale = 1000 / args.images
    print(f"V's encoder on {args.images} images, {args.threads} thread(s), best of {args.repeats}")
    print("| form | s per 1000 images | eager / this | largest difference from eager |")
    print("| --- | --- | --- | --- |")
    for name in forms:
        print(f"| {name} | {best[name] * scale:.3f} | {best['eager'] / best[name]:.2f}x "
              f"| {differences[name]:.1e} |")  # fmt: skip


if __name__ == "__main__":
    main()
