"""Random numbers of the models: counter-based, from a hash of the query.

A model's random numbers are a pure function of its query, so that ``eval`` is
deterministic per (ω_i, ω_o, position) and a sample is reproducible from its
sample numbers: a *stream* is a 32-bit seed hashed from a salt and the query's
floats (``hash_floats``), and its k-th number is ``uniform(seed, k)``. Every
stream and every counter value a model uses is named here, so that no two
decisions share a number by accident (docs/model.md §6).
"""

from __future__ import annotations

import struct

import drjit as dr
import mitsuba as mi

ONE_MINUS_EPS = 0.99999994  # largest float32 below 1
MASK32 = 0xFFFFFFFF

# Salts: one stream per kind of query.
SALT_ANALYTIC_SAMPLE = 0x6d666e31   # the analytic sampler (its shadowing test)
SALT_WALK_SAMPLE = 0x6d666e32       # a walk's sample(): seeded by the sample numbers
SALT_WALK_EVAL = 0x6d666e33         # a walk's eval(): seeded by ω_i, ω_o and the position
SALT_FAITHFUL_SAMPLE = 0x6d666e34   # the faithful sampler (past the neighbours, or blocked)

# Counter slots within a stream.
SLOT_ANALYTIC_SHADOW = 0            # analytic sampler: leave after p, or go on to the mirror t
SLOT_FAITHFUL_BLOCKED = 0           # faithful sampler: the sample leaves, or the neighbours block it
SLOT_FAITHFUL_RETRO = 1             # faithful sampler: a blocked sample skims on, or comes back
SLOT_FAITHFUL_WALL = 2              # faithful sampler: the hidden texel's neighbours are a wall, or not
SLOT_START_FACET = 0xFFFFFFFF       # eval walk: the first facet (sample(): its own sample1)
SLOT_START_HEIGHT = 0xFFFFFFFE      # naive estimator (validation): the first height
SLOT_ROULETTE = 0x7F000000          # + depth: Russian roulette after the bounce at ``depth``
SLOT_CONNECT = 0x60000000           # + 3·depth + k: eval walk's connection sample from ω_o (``slot_connect``)
VERTEX_SLOTS = 4                    # per facet bounce: the escape, then the nested sample's three


def slot_escape(depth):
    """The escape decision of the ray that leaves the vertex at facet bounce ``depth``."""
    return depth * VERTEX_SLOTS


def slot_nested(depth, k):
    """Number k (0: sample1, 1, 2: sample2) of the nested sample at facet bounce ``depth``."""
    return depth * VERTEX_SLOTS + (1 + k)


def slot_connect(depth, k):
    """Number k (0: sample1, 1, 2: sample2) of the eval walk's connection sample from ω_o
    on the facet after the vertex at facet bounce ``depth`` (walk_nee.connect)."""
    return SLOT_CONNECT + depth * 3 + k


def slot_roulette(depth):
    """Russian roulette after the facet bounce at ``depth``."""
    return SLOT_ROULETTE + depth


def bits(x):
    """The IEEE bits of a float32 (Dr.Jit array or, in scalar variants, a Python float)."""
    if isinstance(x, float):
        return struct.unpack("<I", struct.pack("<f", x))[0]
    return dr.reinterpret_array(mi.UInt32, mi.Float32(x))


def _mul32(a, b):
    """32-bit wrapping product (Dr.Jit UInt32 wraps; Python ints of scalar variants need the mask)."""
    return (a * b) & MASK32 if isinstance(a, int) else a * b


def mix32(h):
    """MurmurHash3's 32-bit finaliser: a cheap, well-mixed bijection of UInt32."""
    h = _mul32(h ^ (h >> 16), 0x85EBCA6B)
    h = _mul32(h ^ (h >> 13), 0xC2B2AE35)
    return h ^ (h >> 16)


def hash_floats(salt, *values):
    """A well-mixed 32-bit seed from float inputs (their bits, combined and mixed)."""
    h = mi.UInt32(salt)
    for v in values:
        h = mix32(h ^ _mul32(bits(v) ^ 0x9E3779B9, 0x01000193))
    return h


def uniform(seed, counter):
    """The counter-th uniform number in [0, 1) of the stream ``seed`` (stateless, deterministic)."""
    h = mix32(seed ^ _mul32(mi.UInt32(counter) + 1, 0x9E3779B9))
    return dr.minimum(mi.Float(h >> 8) * (1.0 / 16777216.0), ONE_MINUS_EPS)


def choose(u, p):
    """(u < p, u rescaled to [0, 1) within the branch taken): one uniform serves a binary
    choice of probability p and, rescaled, the next decision (e.g. the first facet by λ_p,
    then the nested sample)."""
    taken = u < p
    rest = dr.select(taken, u / dr.maximum(p, 1e-30), (u - p) / dr.maximum(1.0 - p, 1e-30))
    return taken, dr.clip(rest, 0.0, ONE_MINUS_EPS)
