"""A Dask worker's mfnormal settings: ``dask worker ADDRESS --preload mfnormal.render.worker --variant V``.

The preload runs in each worker process before its first task; with ``--variant``
every chunk that worker renders uses ``V`` (e.g. ``cuda_ad_rgb`` on a GPU node)
instead of the client's ``--variant``. A variant this worker cannot use (no such
build, no GPU) stops the worker at start, with one line. ``--quiet`` silences the
worker's Dask and Tornado logs (the workers of ``--cluster local:N`` share the
client's terminal: a stranger's bytes on their port print nothing).
"""

from __future__ import annotations

import click

from mfnormal.render.cluster import quiet_logs
from mfnormal.render.tasks import set_worker_variant

__all__ = ["dask_setup"]


@click.command()
@click.option("--variant", default=None, help="the Mitsuba variant this worker renders in "
                                              "(default: the client's --variant)")
@click.option("--quiet", is_flag=True, help="silence the worker's Dask and Tornado logs")
def dask_setup(worker, variant, quiet):
    if quiet:
        quiet_logs()
    set_worker_variant(variant)
