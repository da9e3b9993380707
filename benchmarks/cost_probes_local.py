"""Where the default model's render time goes with local statistics (docs/diagnoses.md).

    .venv/bin/python benchmarks/cost_probes_local.py [--scene demo|model] [--pairs 3] [PROBE ...]

Each probe replaces one part of ``faithful`` in this process (its images are wrong; only its
time counts) and is timed against Mitsuba's ``normalmap`` in interleaved warm pairs at 1280×720,
16 spp, with the scene's own materials (benchmarks/run.py's production scenes). Probes:
``as_is``, ``no_hidden`` (the hidden texel's neighbours skipped), ``fill_constant`` (the diffuse
fill's ρ a constant), ``local_constant`` (k and ω_m constants: no grid reads, no mean-plane
arithmetic), ``map_wide`` (``neighbourhood`` 0), ``analytic`` (the paper's analytic model).
"""

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import run as B  # noqa: E402

PROBES = ("as_is", "no_hidden", "fill_constant", "local_constant", "map_wide", "analytic")


def apply_probe(name):
    import drjit as dr
    import mitsuba as mi
    from mfnormal.models import faithful as F
    if name == "no_hidden":
        gated = F._gated

        def skip_hidden(cond, fn, otherwise, gated_=True):
            # The hidden term's branch is the one whose fallback is a literal zero pdf.
            if isinstance(otherwise, tuple) and otherwise[1].state == dr.VarState.Literal:
                return otherwise
            return gated(cond, fn, otherwise, gated_)
        setattr(F, "_gated", skip_hidden)
    elif name == "fill_constant":
        setattr(F.Model, "_fill_rho", lambda self, sp, tx: mi.Spectrum(0.3))
    elif name == "local_constant":
        setattr(F.Model, "local_stats", lambda self, sp: (None, None) if self.local is None else
                (mi.Float(0.2), mi.Vector3f(0.0, 0.0, 1.0)))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("probes", nargs="*", default=["as_is"], choices=PROBES)
    p.add_argument("--scene", default="demo", choices=("demo", "model"))
    p.add_argument("--pairs", type=int, default=3)
    args = p.parse_args()
    B.import_mitsuba()
    mi = B.mi
    assets = B.prepare_assets(Path(tempfile.mkdtemp()), (args.scene,))
    width, height, spp = 1280, 720, 16

    def load(method, **params):
        from mfnormal.io.scene_xml import rewrite_dict
        d = B.scene_dict(args.scene, assets, method, B.NATIVE, width, height, spp)
        if params:
            d = rewrite_dict(d, "normalmap_microfacet", lambda v: v.update(params), "normalmap_microfacet BSDF")
        return mi.load_dict(d)
    base = load("builtin")
    for probe in args.probes:
        apply_probe(probe)
        scene = (load("analytic") if probe == "analytic" else
                 load("faithful", neighbourhood=0.0) if probe == "map_wide" else load("faithful"))
        B.timed_render(base, spp, 1)
        B.timed_render(scene, spp, 1)
        _, _, ratios = B.interleaved_pairs(base, scene, spp, args.pairs)
        print(f"{probe:16s} {statistics.median(ratios):.3f}x  pairs {', '.join(f'{r:.3f}' for r in ratios)}",
              flush=True)
        if probe not in ("as_is", "map_wide", "analytic"):
            break           # a probe changes the process: one per run


if __name__ == "__main__":
    main()
