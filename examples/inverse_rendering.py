"""Inverse rendering: recover a 16² normal map from 3 renders, starting from a flat map.

    python -m examples.inverse_rendering [--method faithful] [--iterations 40] [--out inverse.png]

A plane under a roughplastic (GGX α 0.2) normal-mapped with ``normalmap_microfacet`` is
rendered with the true map under three directional suns (the targets); then the map is
optimised with Adam from a flat map through Mitsuba's ``prb`` integrator, the same method
rendering both. Mitsuba's built-in ``normalmap`` is run beside it for comparison. Prints the
loss and the mean texel error (angle to the true normals) as it goes, and writes a figure:
the loss curves, the error curves, and the true and recovered maps. About half a minute on a
laptop's CPU (llvm_ad_rgb) with the defaults. See ``validation.inverse`` for the pieces and
``validation/inverse_rendering.py`` for every model and the true-geometry target.
"""

from __future__ import annotations

import argparse
from pathlib import Path


import mfnormal  # noqa: E402  (before mitsuba: selects a working libLLVM)
import mitsuba as mi  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--method", default="faithful", help="a key of validation.inverse.METHODS")
    p.add_argument("--iterations", type=int, default=40)
    p.add_argument("--res", type=int, default=32)
    p.add_argument("--spp", type=int, default=8)
    p.add_argument("--out", type=Path, default=Path("inverse_rendering.png"))
    args = p.parse_args(argv)

    mi.set_variant("llvm_ad_rgb")
    mfnormal.register()
    from validation import inverse as I

    setup = I.Setup(res=args.res, spp=args.spp, iterations=args.iterations, lr=0.03)
    results = {}
    for method in ("builtin", args.method):
        targets = I.same_method_targets(setup, method)
        results[method] = I.optimise(setup, method, targets, log=print)
        r = results[method]
        print(f"{method}: texel error {r.error[0]:.2f}° → {r.error[-1]:.2f}° in {r.seconds:.0f} s")

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 5, figsize=(17, 3.4))
    for m, r in results.items():
        ax[0].semilogy(r.loss, label=m)
        ax[1].plot(r.error, label=m)
    ax[0].set(title="loss (MSE, 3 renders)", xlabel="iteration")
    ax[1].set(title="mean texel error (°)", xlabel="iteration")
    ax[0].legend(), ax[1].legend()
    truth = I.normal_image(I.H.encode_normals(I.true_normals(setup)))
    for a, (title, img) in zip(ax[2:], [("true map", truth),
                                        ("built-in", I.normal_image(results["builtin"].texels)),
                                        (args.method, I.normal_image(results[args.method].texels))]):
        a.imshow(img, interpolation="nearest")
        a.set(title=title, xticks=[], yticks=[])
    fig.tight_layout()
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
