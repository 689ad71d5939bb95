"""Eager PyTorch side of ``bench.py --what=deconv``: forward + backward of single ``ConvTranspose2d`` layers.

Run by the peer's python (torch is a benchmark-only tool, never a project dependency):

    .venv-peer/bin/python experiments/torch_layers.py --layers='[[88, 4, 256, 128, 3]]' --repeats=5

Each layer is [N images, input side, C in, C out, kernel]: torch's ``ConvTranspose2d(C in, C out, kernel,
stride 2, padding kernel // 2, output_padding 1)``, the layer ``model.Deconv2x`` computes, timed as the
gradient of sum(y²) wrt input and weights (the same work as the JAX side). Prints one JSON line:
{"torch": version, "threads": n, "layer_s": [median seconds per layer]}.
"""

import argparse
import json
import statistics
import time

import torch


def layer_seconds(n, side, c_in, c_out, kernel, repeats):
    layer = torch.nn.ConvTranspose2d(c_in, c_out, kernel, 2, kernel // 2, output_padding=1)
    x = torch.randn(n, c_in, side, side, requires_grad=True)

    def run():
        x.grad = None
        layer.zero_grad()
        (layer(x) ** 2).sum().backward()

    run()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--layers", required=True, help="JSON list of [N, side, C in, C out, kernel]")
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    layers = json.loads(a.layers)
    print(
        json.dumps(
            {
                "torch": torch.__version__,
                "threads": torch.get_num_threads(),
                "layer_s": [layer_seconds(*layer, a.repeats) for layer in layers],
            }
        )
    )


if __name__ == "__main__":
    main()
