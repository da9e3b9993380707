"""A Dask worker's mfnormal settings: ``dask worker ADDRESS --preload mfnormal.cli.worker --variant V``.

The preload runs in each worker process before its first task; with ``--variant``
every chunk that worker renders uses ``V`` (e.g. ``cuda_ad_rgb`` on a GPU node)
instead of the client's ``--variant``. A variant this worker cannot use (no such
build, no GPU) stops the worker at start, with one line.
"""

from __future__ import annotations

import click

from mfnormal.cli.cluster import set_worker_variant

__all__ = ["dask_setup"]


@click.command()
@click.option("--variant", default=None, help="the Mitsuba variant this worker renders in "
                                              "(default: the client's --variant)")
def dask_setup(worker, variant):
    set_worker_variant(variant)
