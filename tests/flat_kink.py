"""One-sided and central finite differences of the two-facet models at a flat normal map.

One query pair (ω_i at 50°, ω_o at 40° and 2.5 rad), repeated over 2^16 walks at distinct
positions, on a flat 1×4 map; the loss is the mean of eval (RGB mean), d/d the red channel
of the queried texel. Prints each model's AD (forward mode) and, for steps 2e-3, 5e-3 and
1e-2, the one-sided FDs (up, down) and the central one, with standard errors: where up and
down differ by many standard errors the model has no derivative there (docs/differentiable.md).

    python tests/flat_kink.py

(run as a file: the tests' helpers beside it are on its path).
"""
import mfnormal  # noqa: E402  (first: selects a working libLLVM)
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

mi.set_variant("llvm_ad_rgb")
mfnormal.register()

import gradients as G  # noqa: E402
from helpers import encode, make_bsdf, make_si, sph, vec3  # noqa: E402

ALUMINIUM = {"type": "roughconductor", "material": "Al", "distribution": "ggx", "alpha": 0.3}
MODELS = [("analytic", None), ("separable", "specular"), ("nonseparable", "specular"),
          ("separable", "same"), ("nonseparable", "same")]
N = 1 << 16


def main():
    plain = lambda w: 1.0                    # the plain mean of eval  # noqa: E731
    flat = encode(np.array([sph(0)] * 4).reshape(-1, 3))
    wi, wo = np.repeat(sph(50, 0.0)[None], N, 0), vec3(np.repeat(sph(40, 2.5)[None], N, 0))
    si = make_si(wi, 4, texel_index=np.zeros(N, int), p_index=np.arange(N))
    key = ("texel", 0, 0)
    se = lambda x: x.std() / np.sqrt(x.size)
    for model, facet in MODELS:
        b = make_bsdf(ALUMINIUM, flat, model=model, tangent_facet=facet)
        params = mi.traverse(b)
        theta = G._value(params, key)

        def at(x):
            G._with_value(params, key, x)
            with dr.suspend_grad():
                return np.array(G.query_values(b, si, wo, None, c=plain), np.float64)
        ad = G.forward(b, key, si, wo, None, c=plain)
        f0 = at(theta)
        print(f"{model}-{facet}: AD {ad.mean():+.4g} ± {se(ad):.2g}")
        for h in (2e-3, 5e-3, 1e-2):
            up, down = (at(theta + h) - f0) / h, (f0 - at(theta - h)) / h
            print(f"  h={h:g}: up {up.mean():+.4g} ± {se(up):.2g}, down {down.mean():+.4g} ± {se(down):.2g}, "
                  f"central {(0.5 * (up + down)).mean():+.4g}")
        G._with_value(params, key, theta)


if __name__ == "__main__":
    main()
