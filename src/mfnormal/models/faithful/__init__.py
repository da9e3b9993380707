"""The default model: the tilted facet as the true geometry around it shows it (docs/faithful.md).

A texel of a normal map baked from a heightfield is a small piece of surface with
normal ω_p among neighbours whose slopes average to zero. Seen from the camera
direction ω_i (``si.wi``) and lit from ω_o, it shows

    eval(ω_i, ω_o) = V(ω_i)·[ f_p(ω_i, ω_o)·S(ω_o|ω_i)                           Direct
                             + Σ_d w_d·f_p^gl(ω_i, d)·(1 − S(d|ω_i)), M(d) = ω_o   Skim, Retro
                             + B(ω_i)·ρ_fill(ω_i)·⟨ω_o, ω_g⟩/π ]                 Fill
                   + (1 − V(ω_i))·f_g(ω_i, ω_o)                                 Hidden

- the lobes (:mod:`.lobes`): the facet lit directly; the glossy light the neighbours block,
  bounced on past them or back the way it came; the diffuse light they block; the neighbours
  where the texel is hidden;
- f_p, f_g: the nested f·cos on the facet (frame ω_p) and on the macro surface
  (frame ω_g); f_p^gl its non-diffuse components;
- V(ω) = min(1, R(ω)·G1(ω)): the share of the texel's footprint in which a ray from ω
  hits the texel, R its projected area and G1 Smith's masking by neighbours whose slopes
  have the map's principal rms slopes σ1, σ2 (Beckmann), or with local statistics their
  neighbourhood's, k times those;
- S(ω|ω_i) = χ⁺(⟨ω,ω_p⟩)χ⁺(⟨ω,ω_g⟩)·(1 + Λ(ω_i)) / (1 + Λ(ω_i) + Λ(ω)): the chance that a
  visible point of the texel sees ω past its neighbours (height-correlated Smith);
- light the neighbours block is not lost: its glossy part skims on past them or comes back
  the way it came (M, piecewise isometries: energy exact; w_d the share of each), its
  diffuse part leaves as a cosine lobe weighted by B(ω_i), the blocked share of a
  Lambertian facet's light (a table), and ρ_fill, what one bounce on a neighbour returns.

So the white furnace is exactly the nested albedo (1 for white facets), energy never
exceeds it, nothing turns black, and the texel keeps classic normal mapping's relief
under directional light (the ⟨ω_o, ω_p⟩ of f_p). The model is **not reciprocal** in
the macro frame: a reciprocal BSDF that is white in the white furnace has the same
view-averaged response to every light direction for every texel, i.e. no relief
(docs/faithful.md §2). Light tracing sees the adjoint (``TransportMode.Importance``):
eval*(a, b) = eval(b, a)·⟨b, ω_g⟩ / ⟨a, ω_g⟩, so path tracing and light tracing agree.

A nested BSDF that transmits is normal-mapped on both sides (docs/faithful.md §7): the facet's
transmitted light leaves on the far side of the macro surface (folded there from the camera's
side), and a camera below the surface sees the mirrored heightfield (:class:`Texel`).

The package, one module per idea:

- :mod:`.texel`: the texel among its neighbours, seen from ω_i (V, S, B, the bounce M);
- :mod:`.tables`: the map's slopes σ1, σ2, φ_e, the blocked-light table B and the local
  statistics' grids (computed by :mod:`mfnormal.models.neighbourhood`);
- :mod:`.lobes`, :mod:`.transmission`: the lobes, each with its value, density and adjoint;
- :mod:`.model`: eval, pdf and the radiance-mode sampler over the lobes;
- :mod:`.adjoint`: light tracing's eval*, its sampler and its pdf;
- :mod:`.nested`: the nested BSDF's queries on the facet and on the macro surface.
"""

from mfnormal.models.faithful.lobes import FILL_SHARE_MAX, FILL_SHARE_MIN, HORIZON_MU
from mfnormal.models.faithful.model import Model
from mfnormal.models.faithful.nested import Components, macro_frame
from mfnormal.models.faithful.tables import MILD_SLOPE, MapStatistics
from mfnormal.models.faithful.texel import MEAN_PLANE_MIN, OWN_PLANE_K, RETRO_K, RETRO_SLOPE, Texel

__all__ = ["Components", "FILL_SHARE_MAX", "FILL_SHARE_MIN", "HORIZON_MU", "MEAN_PLANE_MIN", "MILD_SLOPE",
           "MapStatistics", "Model", "OWN_PLANE_K", "RETRO_K", "RETRO_SLOPE", "Texel", "macro_frame"]

