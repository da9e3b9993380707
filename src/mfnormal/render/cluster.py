"""Rendering on a Dask.distributed cluster: ``mfnormal render|compare --cluster local:N|ADDRESS``.

Dask.distributed is the engine (the optional extra ``pip install 'mfnormal[cluster]'``):
pure Python, a ``LocalCluster`` of worker processes on one machine (``local:N``), and
the same scheduler address whether its workers were started by hand (``dask
scheduler`` / ``dask worker``), by ``dask-jobqueue`` on SLURM/PBS/SGE or by
``dask-kubernetes``; it resubmits the tasks of a lost worker and retries failed ones.

What travels:

- the scene (:func:`mfnormal.render.bundle.scene_spec`): an XML scene's text with every file it
  names, or a glTF file with the buffers and images its JSON names, read on the client; nothing
  else (or, with ``shared=True``, nothing: the workers read the scene's path);
- the chunks: a render's samples split as :func:`mfnormal.render.passes.schedule` splits a
  local render into passes (the same ``(spp, seed)`` for the same ``--seed`` and chunk
  count), each one task; their images come back and are merged in schedule order by
  :func:`mfnormal.render.passes.weighted_mean`, the local render's accumulator, so a cluster
  render equals the local render of the same passes up to the order of the film's
  floating-point sums;
- the versions: every worker must run the client's Mitsuba, Dr.Jit and mfnormal (its
  source, hashed), checked when connecting (:meth:`Cluster.check_workers`) and again by
  every task (:mod:`mfnormal.render.tasks`, what the workers run).

A worker renders in the client's ``--variant`` unless it was started with its own
(``dask worker ADDRESS --preload mfnormal.render.worker --variant cuda_ad_rgb``, see
:mod:`mfnormal.render.worker`). Tasks in one worker process run one at a time.
"""

from __future__ import annotations

import asyncio
import logging
import os
import re
import time
import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mfnormal.io.inputs import CLIError, check_regular_file
from mfnormal.io.messages import one_line
from mfnormal.render.bundle import SceneSpec
from mfnormal.render.passes import MIN_THREADS, weighted_mean
from mfnormal.render.tasks import (Env, held_files, mismatch, render_chunk, render_rgb_job, variant_job,
                                   versions, worker_info)

__all__ = ["CLUSTER_HELP", "SCHEMES", "Target", "parse_cluster", "security", "quiet_logs", "Cluster"]

CLUSTER_HELP = ("render on a Dask.distributed cluster: local:N (N worker processes on this "
                "machine, listening on loopback only) or a scheduler's address (tcp://HOST:PORT, "
                "tls://HOST:PORT with --cluster-tls-*); needs pip install 'mfnormal[cluster]'")
#: The address schemes of ``--cluster ADDRESS``; those that encrypt need certificates.
SCHEMES = ("tcp", "tls", "ws", "wss")
SECURE_SCHEMES = ("tls", "wss")
#: How often a failed task is retried (on any worker); a lost worker's tasks are
#: resubmitted by the scheduler on its own (``distributed.scheduler.allowed-failures``).
RETRIES = 2
_ADDRESS = re.compile(r"^(?:(\w+)://)?(\[[0-9a-fA-F:]+\]|[\w.-]+):(\d{1,5})/?$")


# ---------------------------------------------------------------------------
# --cluster
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Target:
    """Where to render: ``local`` with ``workers`` processes, or a scheduler ``address``;
    ``tls`` the (CA, certificate, key) files of ``--cluster-tls-*`` (empty: none given)."""
    text: str
    workers: int = 0
    address: str = ""
    tls: tuple = ()


def parse_cluster(text: str, tls: tuple = ()) -> Target:
    """``--cluster``'s value and the ``--cluster-tls-*`` files ``tls`` (CA, certificate,
    key; None where not given), checked (and Dask.distributed importable), or :class:`CLIError`."""
    value = text.strip()
    m_local = re.fullmatch(r"local(?::(.*))?", value)
    if m_local:
        n = m_local.group(1)
        if n is None or not n.strip().isdigit() or not 1 <= int(n) <= 1024:
            raise CLIError(f"--cluster {text}: expected local:N with N worker processes, 1 to 1024")
        target = Target(text, workers=int(n))
    else:
        m = _ADDRESS.match(value)
        if not m or not 1 <= int(m.group(3)) <= 65535:
            raise CLIError(f"--cluster {text}: expected local:N (N worker processes on this machine) "
                           "or a scheduler address, tcp://HOST:PORT or HOST:PORT")
        if m.group(1) and m.group(1).lower() not in SCHEMES:
            raise CLIError(f"--cluster {text}: the {m.group(1)}:// protocol is not supported; use "
                           f"{', '.join(s + '://' for s in SCHEMES)} (or local:N)")
        target = Target(text, address=f"{(m.group(1) or 'tcp').lower()}://{value.split('://')[-1]}")
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise CLIError(f"--cluster needs Dask.distributed: pip install 'mfnormal[cluster]'") from None
    return Target(target.text, target.workers, target.address, _check_tls(target, tls))


def _check_tls(target: Target, tls: tuple) -> tuple:
    """The ``--cluster-tls-*`` files (CA, certificate, key or None), checked against the
    target: a TLS address needs certificates (these or Dask's configuration), a tcp:// one
    takes none; each file a regular file."""
    ca, cert, key = tuple(tls) + (None,) * (3 - len(tls))
    scheme = target.address.split("://")[0]
    if not any((ca, cert, key)):
        if scheme in SECURE_SCHEMES and not _dask_tls_configured():
            raise CLIError(f"--cluster {target.text}: a {scheme}:// scheduler needs certificates: "
                           "--cluster-tls-ca, --cluster-tls-cert and --cluster-tls-key, or Dask's "
                           "configuration (DASK_DISTRIBUTED__COMM__TLS__CA_FILE, "
                           "..._CLIENT__CERT, ..._CLIENT__KEY)")
        return ()
    if target.address and scheme not in SECURE_SCHEMES:
        raise CLIError(f"--cluster {target.text}: --cluster-tls-* need a tls:// scheduler address "
                       f"({scheme}:// is not encrypted)")
    if not (ca and cert):
        raise CLIError("--cluster-tls-ca and --cluster-tls-cert go together (and --cluster-tls-key, "
                       "unless the certificate file holds the key)")
    for flag, path in (("--cluster-tls-ca", ca), ("--cluster-tls-cert", cert), ("--cluster-tls-key", key)):
        if path is not None:
            check_regular_file(path, f"{flag} {path}", f"{flag} {path}: no such file")
    _check_tls_files(ca, cert, key)
    return (str(ca), str(cert), None if key is None else str(key))


def _check_tls_files(ca, cert, key) -> None:
    """The ``--cluster-tls-*`` files as OpenSSL reads them, before any work (OpenSSL's own words
    came as "cannot reach the scheduler ([SSL] PEM lib)"): the CA file holds a certificate, the
    certificate file a certificate and, without ``--cluster-tls-key``, its key; the key file a key
    that is the certificate's. An encrypted key is refused, not asked for on the terminal."""
    import ssl

    def no_passphrase():
        raise ValueError("encrypted")

    try:
        ssl.create_default_context(cafile=str(ca))
    except ssl.SSLError as exc:
        raise CLIError(f"--cluster-tls-ca {ca}: no CA certificate in this file ({exc.reason}); give "
                       "the PEM certificate of the authority that signed the scheduler's") from None
    try:
        ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT).load_cert_chain(
            str(cert), None if key is None else str(key), password=no_passphrase)
    except (ssl.SSLError, ValueError) as exc:
        raise CLIError(_key_message(cert, key, getattr(exc, "reason", None))) from None


def _key_message(cert, key, reason) -> str:
    """The one line for a certificate and key (``key`` None: in the certificate's file) that
    OpenSSL refused with ``reason``."""
    if key is None:
        return (f"--cluster-tls-cert {cert}: no certificate with its private key in this file; give "
                "the key with --cluster-tls-key FILE, or a PEM file that holds both (the key unencrypted)")
    if reason == "KEY_VALUES_MISMATCH":
        return (f"--cluster-tls-key {key} is not the key of --cluster-tls-cert {cert} (key values "
                "mismatch); give the certificate's own key")
    if b"CERTIFICATE-----" not in Path(cert).read_bytes():
        return f"--cluster-tls-cert {cert}: no certificate in this file; give the client's PEM certificate"
    if b"PRIVATE KEY-----" not in Path(key).read_bytes():
        return f"--cluster-tls-key {key}: no private key in this file; give the certificate's PEM key"
    why = f": {reason}" if reason else ""
    return (f"--cluster-tls-key {key}: the key is encrypted (or OpenSSL cannot read it{why}); give the "
            "certificate's PEM key without a passphrase")


def _dask_tls_configured() -> bool:
    """Whether Dask's own configuration names a CA and a client certificate."""
    import dask

    return bool(dask.config.get("distributed.comm.tls.ca-file", None)
                and dask.config.get("distributed.comm.tls.client.cert", None))


def security(tls: tuple, local: bool = False):
    """Dask's ``Security`` of the ``--cluster-tls-*`` files (for ``local``, the scheduler's
    and workers' too), or None (Dask's own configuration)."""
    if not tls:
        return None
    from distributed import Security

    ca, cert, key = tls
    roles = ("client", "scheduler", "worker") if local else ("client",)
    files = {f"tls_{role}_{kind}": path for role in roles for kind, path in (("cert", cert), ("key", key))
             if path is not None}
    return Security(tls_ca_file=ca, require_encryption=True, **files)


def quiet_logs() -> None:
    """Silence Dask's and Tornado's loggers in this process: what they would say (a
    connection that sent bytes that are not Dask's, a worker that left) the client says in
    one line, or it is not the user's business."""
    for name in ["distributed", "tornado", *logging.root.manager.loggerDict]:
        if name.startswith(("distributed", "tornado")):
            logging.getLogger(name).setLevel(logging.CRITICAL + 1)


# ---------------------------------------------------------------------------
# The client's side
# ---------------------------------------------------------------------------

def _local_cluster(target: Target):
    """The ``LocalCluster`` of ``local:N``: scheduler, nannies and workers on loopback only,
    no dashboard (the scheduler's health and metrics routes on a loopback port of its
    own; Dask's default binds the dashboard to every interface), the workers' logs as
    quiet as the client's (:mod:`mfnormal.render.worker`); over TLS with the
    ``--cluster-tls-*`` certificates when given."""
    from distributed import LocalCluster

    sec = security(target.tls, local=True)
    return LocalCluster(n_workers=target.workers, threads_per_worker=1, processes=True,
                        host="127.0.0.1", protocol="tls://" if sec else "tcp://", security=sec,
                        dashboard_address=None, scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                        silence_logs=logging.CRITICAL, memory_limit=0,
                        preload=["mfnormal.render.worker"], preload_argv=["--quiet"])


def _handshake(address: str, timeout: float, args: dict) -> None:
    """Open and close a connection (Dask's connection ``args``) to the scheduler at ``address``,
    Dask's handshake included, within ``timeout`` seconds; raises TimeoutError or OSError.
    Dask bounds the TCP connection and a TLS handshake, not the handshake's reply: a
    ``tcp://`` peer that accepts and never answers would hold ``Client()`` for ever."""
    from distributed.comm import connect

    async def probe():
        comm = await connect(address, timeout=timeout, **args)
        await comm.close()

    try:
        asyncio.run(asyncio.wait_for(probe(), timeout))
    except asyncio.TimeoutError:
        raise TimeoutError(f"no answer within {timeout:g} s: is it a Dask scheduler?") from None


class Cluster:
    """A connection to the cluster of ``target`` (a context manager): starts the
    ``LocalCluster`` of ``local:N``, or connects to a scheduler and waits up to ``timeout``
    seconds for a worker; checks every worker's versions. Tasks render in ``variant``."""

    def __init__(self, target: Target, variant: str, timeout: float = 60.0):
        self.target, self.timeout = target, float(timeout)
        self.client = self._local = None
        self.info: dict = {}
        threads = max(MIN_THREADS, (os.cpu_count() or 1) // target.workers) if target.workers else None
        self.env = Env(variant, versions(), threads)
        self._token = uuid.uuid4().hex[:12]
        self._submitted = 0

    def __enter__(self):
        try:
            self._connect()
            self.info = self.check_workers()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc):
        self.close()

    def _connect(self):
        from distributed import Client, Security

        quiet_logs()                # their errors are ours to tell, in one line
        if self.target.workers:
            try:
                self._local = _local_cluster(self.target)
                self.client = Client(self._local, security=security(self.target.tls, local=True))
            except Exception as exc:
                raise CLIError(f"--cluster {self.target.text}: cannot start the local cluster: "
                               f"{one_line(exc)}") from None
            return
        try:
            sec = security(self.target.tls) or Security()
            _handshake(self.target.address, self.timeout, sec.get_connection_args("client"))
            self.client = Client(self.target.address, timeout=f"{self.timeout}s", security=sec)
        except (OSError, TimeoutError, ValueError, TypeError) as exc:
            raise CLIError(f"--cluster {self.target.text}: cannot reach the scheduler "
                           f"({one_line(exc)})") from None
        try:
            self.client.wait_for_workers(1, timeout=self.timeout)
        except (TimeoutError, OSError):
            raise CLIError(f"--cluster {self.target.text}: no worker joined the scheduler within "
                           f"{self.timeout:g} s") from None

    def close(self):
        for thing in (self.client, self._local):
            if thing is not None:
                try:
                    thing.close()
                except Exception:   # noqa: BLE001  (closing a cluster that is already gone)
                    pass
        self.client = self._local = None

    def workers(self) -> int:
        return len(self.client.nthreads())

    def check_workers(self) -> dict:
        """Every worker's {'versions', 'variant'}, after refusing any whose versions differ."""
        info = self.client.run(worker_info)
        for address, item in info.items():
            problem = item["problem"] and f"worker {address}: {item['problem']}"
            problem = problem or mismatch(item["versions"], self.env.versions, f"worker {address}")
            if problem:
                raise CLIError(problem)
        return info

    def variants(self, info: dict) -> str:
        """The variants the workers render in, as text."""
        names = sorted({item["variant"] or self.env.variant for item in info.values()})
        return ", ".join(names)

    # -- Submitting and collecting ------------------------------------------------------

    def _send(self, files: dict, digest: str):
        """The files as a task's result: a lost copy is recomputed from the scheduler's graph."""
        if not files:
            return None
        with warnings.catch_warnings():     # "large object in the graph": these files, on purpose
            warnings.simplefilter("ignore", UserWarning)
            return self.client.submit(held_files, files, key=f"mfnormal-files-{digest}", pure=False)

    def _submit(self, function, *args):
        self._submitted += 1
        key = f"mfnormal-{function.__name__}-{self._token}-{self._submitted}"
        return self.client.submit(function, self.env, *args, key=key, retries=RETRIES, pure=False)

    def _in_order(self, futures: list, progress=None):
        """The futures' results in their order, as they come (``progress(done, total)`` on
        each); :class:`CLIError` when a task fails for good or the cluster has had no worker
        for ``timeout`` seconds."""
        from distributed import wait

        pending, done, results, nxt = set(futures), 0, {}, 0
        index = {f.key: i for i, f in enumerate(futures)}
        workerless = None
        while nxt < len(futures):
            try:
                finished, pending = wait(pending, timeout=1.0, return_when="FIRST_COMPLETED")
            except TimeoutError:
                finished = set()
            except Exception as exc:  # noqa: BLE001  (cancelled: the client lost its scheduler)
                raise CLIError(f"lost the cluster with {len(futures) - done} of {len(futures)} "
                               f"tasks left: {one_line(exc)}") from None
            for f in finished:
                results[index[f.key]] = self._result(f)
                done += 1
                if progress:
                    progress(done, len(futures))
            while nxt in results:
                yield results.pop(nxt)
                nxt += 1
            workerless = self._watch(workerless, len(futures) - done, len(futures))

    def _result(self, future):
        try:
            return future.result()
        except Exception as exc:  # noqa: BLE001  (a task that failed on every try, a lost cluster)
            raise CLIError(f"a task failed on the cluster: {one_line(exc)}") from None
        finally:
            future.release()

    def _watch(self, since, left: int, total: int):
        """When the cluster lost its last worker (None while it has one); CLIError after
        ``timeout`` seconds without any."""
        if not left:
            return None
        try:
            alive = self.workers() > 0
        except Exception as exc:  # noqa: BLE001  (the scheduler is gone)
            raise CLIError(f"lost the cluster's scheduler with {left} of {total} tasks left: "
                           f"{one_line(exc)}") from None
        if alive:
            return None
        since = since or time.monotonic()
        if time.monotonic() - since > self.timeout:
            raise CLIError(f"the cluster has had no worker for {self.timeout:g} s with {left} of "
                           f"{total} tasks left")
        return since

    def render(self, spec: SceneSpec, files: dict, passes: list, progress=None) -> np.ndarray:
        """The mean of the chunks ``(spp, seed)`` of ``passes``, rendered on the workers and
        merged in order by the local render's accumulator (float64, H × W × C)."""
        sent = self._send(files, spec.files)
        futures = [self._submit(render_chunk, spec, sent, spp, seed) for spp, seed in passes]
        chunks = ((spp, img) for spp, img, _ in self._in_order(futures, progress))
        return weighted_mean(chunks)

    def render_rgb_many(self, jobs: list, files: dict, digest: str) -> list:
        """Submit :func:`render_rgb_job` for each ``(spec, spp, seed, per_pass)`` of ``jobs``;
        returns a function that collects their (RGB, seconds) in order."""
        sent = self._send(files, digest)
        futures = [self._submit(render_rgb_job, spec, sent, *job) for spec, *job in jobs]
        return lambda: list(self._in_order(futures))

    def call_each(self, function, calls: list):
        """Submit ``function(*args, **kwargs)`` for each ``(args, kwargs)`` of ``calls``, in the
        client's variant on the workers (:func:`mfnormal.render.tasks.variant_job`); returns a
        function that collects the results in order."""
        futures = [self._submit(variant_job, function, args, kwargs) for args, kwargs in calls]
        return lambda: list(self._in_order(futures))
