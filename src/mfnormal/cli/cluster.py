"""Rendering on a Dask.distributed cluster: ``mfnormal render|compare --cluster local:N|ADDRESS``.

Dask.distributed is the engine (the optional extra ``pip install 'mfnormal[cluster]'``):
pure Python, a ``LocalCluster`` of worker processes on one machine (``local:N``), and
the same scheduler address whether its workers were started by hand (``dask
scheduler`` / ``dask worker``), by ``dask-jobqueue`` on SLURM/PBS/SGE or by
``dask-kubernetes``; it resubmits the tasks of a lost worker and retries failed ones.

What travels:

- the scene (:func:`scene_spec`): an XML scene's text with every file it names
  (``<include>``, ``filename`` and the plugin's ``normalmap`` and ``heightmap``, after ``$``
  substitution)
  read on the client and renamed after its content; a glTF file with the buffers and
  images its JSON names. Nothing else is read. With ``shared=True`` the workers load the
  scene from its path (a file system they share with the client) and nothing travels;
- the chunks: a render's samples split as :func:`mfnormal.cli.rendering.schedule` splits a
  local render into passes (the same ``(spp, seed)`` for the same ``--seed`` and chunk
  count), each one task; their images come back and are merged in schedule order by
  :func:`mfnormal.cli.rendering.weighted_mean`, the local render's accumulator, so a cluster
  render equals the local render of the same passes up to the order of the film's
  floating-point sums;
- the versions: every worker must run the client's Mitsuba, Dr.Jit and mfnormal (its
  source, hashed), checked when connecting (:meth:`Cluster.check_workers`) and again by
  every task.

A worker renders in the client's ``--variant`` unless it was started with its own
(``dask worker ADDRESS --preload mfnormal.cli.worker --variant cuda_ad_rgb``, see
:mod:`mfnormal.cli.worker`). Tasks in one worker process run one at a time.
"""

from __future__ import annotations

import asyncio
import hashlib
import importlib.metadata
import json
import logging
import os
import re
import threading
import time
import urllib.parse
import uuid
import warnings
import xml.etree.ElementTree as ET
from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from mfnormal.cli.rendering import MIN_THREADS
from mfnormal.io.messages import one_line
from mfnormal.io.inputs import FILE_STRINGS, CLIError, check_regular_file

__all__ = ["CLUSTER_HELP", "SCHEMES", "Target", "parse_cluster", "security", "quiet_logs", "Cluster",
           "SceneSpec", "scene_spec", "xml_bundle", "files_digest", "versions", "render_chunk",
           "render_rgb_job", "set_worker_variant"]

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
    if key is None:
        _check_holds_key(cert)
    return (str(ca), str(cert), None if key is None else str(key))


def _check_holds_key(cert) -> None:
    """A ``--cluster-tls-cert`` given without ``--cluster-tls-key`` holds its key too (OpenSSL
    says only "PEM lib"); an encrypted key is refused, not asked for on the terminal."""
    import ssl

    def no_passphrase():
        raise ValueError("encrypted")

    try:
        ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT).load_cert_chain(str(cert), password=no_passphrase)
    except (ssl.SSLError, ValueError):
        raise CLIError(f"--cluster-tls-cert {cert}: no certificate with its private key in this file; "
                       "give the key with --cluster-tls-key FILE, or a PEM file that holds both "
                       "(the key unencrypted)") from None


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
# Versions
# ---------------------------------------------------------------------------

@lru_cache(maxsize=None)
def _package_version() -> str:
    """mfnormal's version and a hash of its source (a changed checkout is another version)."""
    try:
        version = importlib.metadata.version("mfnormal")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    digest = hashlib.sha256()
    package = Path(__file__).resolve().parents[1]
    for path in sorted(package.rglob("*.py")):
        digest.update(path.relative_to(package).as_posix().encode() + b"\0" + path.read_bytes())
    return f"{version}+{digest.hexdigest()[:10]}"


def versions() -> dict:
    """The versions a worker must share with its client."""
    import drjit as dr
    import mitsuba as mi

    return {"mitsuba": mi.__version__, "drjit": dr.__version__, "mfnormal": _package_version()}


def _mismatch(theirs: dict, ours: dict, who: str) -> str | None:
    """One line naming what differs between ``theirs`` and the client's ``ours``, or None."""
    diff = [f"{k} {theirs.get(k)} (the client has {v})" for k, v in ours.items() if theirs.get(k) != v]
    if not diff:
        return None
    return (f"{who} runs {', '.join(diff)}; every worker needs the client's Mitsuba, Dr.Jit and "
            "mfnormal: refusing to mix them")


# ---------------------------------------------------------------------------
# The scene, as it travels
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class SceneSpec:
    """A scene as the workers load it: ``kind`` 'xml' or 'gltf'; ``source`` the XML text,
    the bundle name of the glTF file, or (``shared``) the scene's path; ``params`` the
    ``-D`` values (XML) or :func:`mfnormal.io.gltf.load_gltf` options (glTF); ``files`` the
    digest of the files that travel with it."""
    kind: str
    source: str
    params: tuple = ()
    shared: bool = False
    files: str = ""
    limits: object = None


def _bundle_name(data: bytes, name: str) -> str:
    safe = re.sub(r"[^\w.-]", "_", Path(name).name)
    return f"{hashlib.sha256(data).hexdigest()[:16]}_{safe}"


def _add(files: dict, data: bytes, name: str) -> str:
    key = _bundle_name(data, name)
    files[key] = data
    return key


def _resolver(folder: Path):
    """Mitsuba's file resolver with ``folder`` searched first (what ``load_file`` uses)."""
    import mitsuba as mi

    current = mi.file_resolver() if hasattr(mi, "file_resolver") else mi.Thread.thread().file_resolver()
    resolver = mi.FileResolver(current)
    resolver.prepend(str(folder))
    return resolver


def _named_file(value: str, resolver) -> Path | None:
    path = Path(str(resolver.resolve(value)))
    return path if path.is_file() else None


def _bundle_tree(root: ET.Element, folder: Path, values: dict, files: dict, depth: int) -> None:
    """Rename, in place, every file ``root`` names to its bundle name (added to ``files``);
    ``<include>``\\ d files are bundled the same way, recursively."""
    from mfnormal.io.scene_xml import defaults, substitute

    resolver = _resolver(folder)
    for el in root.iter():
        attr = "filename" if "filename" in el.attrib else None
        if attr is None and el.tag == "string" and el.get("name") in FILE_STRINGS:
            attr = "value"
        if attr is None:
            continue
        path = _named_file(substitute(el.get(attr), values), resolver)
        if path is None:
            continue                  # not a file: Mitsuba's own error (the client loaded it)
        if el.tag == "include" and depth < 16:
            sub = ET.fromstring(path.read_bytes())
            _bundle_tree(sub, path.parent, {**defaults(sub), **values}, files, depth + 1)
            data = ET.tostring(sub, encoding="utf-8")
        else:
            data = path.read_bytes()
        el.set(attr, _add(files, data, path.name))


def xml_bundle(text: str, folder, params: dict) -> tuple:
    """(XML text, ``-D`` values, files) of the scene ``text`` whose relative file names
    are relative to ``folder``: every file it names (and only those) read into ``files``
    (bundle name → bytes), the text renamed to match; the ``-D`` values it no longer
    uses (those that only named files) dropped."""
    from mfnormal.io.scene_xml import defaults, references

    root = ET.fromstring(text)
    files: dict = {}
    _bundle_tree(root, Path(folder).resolve(), {**defaults(root), **params}, files, 0)
    text = ET.tostring(root, encoding="unicode")
    texts = [text] + [d.decode("utf-8", "replace") for k, d in files.items() if k.endswith(".xml")]
    used = {k: v for k, v in params.items() if any(references(t, k) for t in texts)}
    return text, used, files


def _gltf_bundle(path: Path) -> tuple:
    """(bundle name of the glTF file, files): a ``.glb`` alone, or a ``.gltf`` with the
    buffers and images its JSON names by relative URI (renamed to match)."""
    files: dict = {}
    data = path.read_bytes()
    if path.suffix.lower() == ".gltf":
        doc = json.loads(data)
        for item in doc.get("buffers", []) + doc.get("images", []):
            uri = item.get("uri")
            if not uri or uri.startswith("data:"):
                continue
            named = path.parent / urllib.parse.unquote(uri)
            if named.is_file():
                item["uri"] = _add(files, named.read_bytes(), named.name)
        data = json.dumps(doc).encode()
    return _add(files, data, path.name), files


def scene_spec(path, params: dict, gltf_options: dict | None = None, shared: bool = False,
               limits=None) -> tuple:
    """(:class:`SceneSpec`, files) of the scene file ``path`` with ``-D`` ``params`` (an XML
    scene) or ``gltf_options`` (a glTF file)."""
    path = Path(path).resolve()
    kind = "xml" if gltf_options is None else "gltf"
    values = params if gltf_options is None else gltf_options
    if shared:
        return SceneSpec(kind, str(path), tuple(sorted(values.items())), True, limits=limits), {}
    if kind == "gltf":
        source, files = _gltf_bundle(path)
    else:
        source, values, files = xml_bundle(path.read_text(encoding="utf-8"), path.parent, params)
    return SceneSpec(kind, source, tuple(sorted(values.items())), False, files_digest(files), limits), files


def files_digest(files: dict) -> str:
    return hashlib.sha256("\0".join(sorted(files)).encode()).hexdigest()[:16]


# ---------------------------------------------------------------------------
# The workers' side
# ---------------------------------------------------------------------------

#: The variant this worker process was started with (:mod:`mfnormal.cli.worker`), if any, and
#: why it cannot use it (then it refuses every task: Dask only logs a failed preload).
WORKER_VARIANT: str | None = None
WORKER_PROBLEM: str | None = None
_LOCK = threading.Lock()
_SCENES: OrderedDict = OrderedDict()


@dataclass(frozen=True)
class Env:
    """What a task needs besides its scene: the client's variant, versions and, for
    ``local:N``, the Dr.Jit threads of each worker (None: all of its machine's; never
    under :data:`MIN_THREADS`)."""
    variant: str
    versions: dict
    threads: int | None = None


def set_worker_variant(variant: str | None) -> None:
    """Make ``variant`` this worker process's variant (every task renders in it)."""
    global WORKER_VARIANT, WORKER_PROBLEM
    WORKER_VARIANT, WORKER_PROBLEM = variant or None, None
    if variant:
        try:
            _use_variant(variant)
        except RuntimeError as exc:
            WORKER_PROBLEM = str(exc)
            raise


def _use_variant(variant: str):
    from mfnormal.cli.rendering import use_variant

    return use_variant(variant, RuntimeError, f"variant '{variant}' is not available in this worker's Mitsuba build",
                       f"this worker cannot use variant '{variant}'")


def _prepare(env: Env):
    """Mitsuba in the worker's variant, after the version check; raises RuntimeError."""
    import drjit as dr

    problem = WORKER_PROBLEM or _mismatch(versions(), env.versions, f"worker (pid {os.getpid()})")
    if problem:
        raise RuntimeError(problem)
    mi = _use_variant(WORKER_VARIANT or env.variant)
    threads = max(MIN_THREADS, env.threads or dr.thread_count())
    if dr.thread_count() != threads:
        dr.set_thread_count(threads)
    return mi


def _materialise(files: dict, digest: str) -> Path:
    """A folder of this worker holding ``files`` (each written once, atomically)."""
    import tempfile

    try:
        from distributed import get_worker
        base = Path(get_worker().local_directory)
    except (ImportError, ValueError):
        base = Path(tempfile.gettempdir())
    folder = base / "mfnormal-scenes" / digest
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in files.items():
        target = folder / name
        if not target.exists():
            tmp = folder / f".{name}.{os.getpid()}.tmp"
            tmp.write_bytes(data)
            os.replace(tmp, target)
    return folder


def _scene(mi, spec: SceneSpec, files: dict | None):
    """The loaded scene of ``spec`` (the last two are kept per process). Its warnings are
    not repeated: the client loaded it first and showed them."""
    key = (mi.variant(), spec)
    if key in _SCENES:
        _SCENES.move_to_end(key)
        return _SCENES[key]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = _load(mi, spec, files)
    _SCENES[key] = scene
    while len(_SCENES) > 2:
        _SCENES.popitem(last=False)
    return scene


def _load(mi, spec: SceneSpec, files: dict | None):
    params = dict(spec.params)
    folder = None if spec.shared else _materialise(files or {}, spec.files)
    if spec.kind == "gltf":
        from mfnormal.io.gltf import load_gltf
        path = spec.source if spec.shared else folder / spec.source
        scene = mi.load_dict(load_gltf(path, limits=spec.limits, **params))
    elif spec.shared:
        scene = mi.load_file(spec.source, **params)
    else:
        path = folder / _bundle_name(spec.source.encode(), "scene.xml")
        if not path.exists():
            path.write_text(spec.source, encoding="utf-8")
        scene = mi.load_file(str(path), **params)
    return scene


def render_chunk(env: Env, spec: SceneSpec, files, spp: int, seed: int) -> tuple:
    """One chunk, on a worker: (spp, the film's channels as float32 H × W × C, variant)."""
    with _LOCK:
        mi = _prepare(env)
        scene = _scene(mi, spec, files)
        return spp, np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float32), mi.variant()


def render_rgb_job(env: Env, spec: SceneSpec, files, spp: int, seed: int, per_pass: int) -> tuple:
    """:func:`mfnormal.cli.rendering.render_rgb` on a worker: (RGB, render seconds)."""
    from mfnormal.cli.rendering import render_rgb

    with _LOCK:
        mi = _prepare(env)
        scene = _scene(mi, spec, files)
        t0 = time.perf_counter()
        return render_rgb(scene, spp, seed, per_pass), time.perf_counter() - t0


def bsdf_checks_job(env: Env, method, samples: int, repeats: int) -> dict:
    """:func:`mfnormal.report.bsdf_checks.bsdf_checks` on a worker."""
    from mfnormal.report.bsdf_checks import bsdf_checks

    with _LOCK:
        _prepare(env)
        return bsdf_checks(method, samples, repeats=repeats)


def _worker_info() -> dict:
    return {"versions": versions(), "variant": WORKER_VARIANT, "problem": WORKER_PROBLEM}


def _files(files: dict) -> dict:
    return files


# ---------------------------------------------------------------------------
# The client's side
# ---------------------------------------------------------------------------

def _local_cluster(target: Target):
    """The ``LocalCluster`` of ``local:N``: scheduler, nannies and workers on loopback only,
    no dashboard (the scheduler's health and metrics routes on a loopback port of its
    own; Dask's default binds the dashboard to every interface), the workers' logs as
    quiet as the client's (:mod:`mfnormal.cli.worker`); over TLS with the
    ``--cluster-tls-*`` certificates when given."""
    from distributed import LocalCluster

    sec = security(target.tls, local=True)
    return LocalCluster(n_workers=target.workers, threads_per_worker=1, processes=True,
                        host="127.0.0.1", protocol="tls://" if sec else "tcp://", security=sec,
                        dashboard_address=None, scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                        silence_logs=logging.CRITICAL, memory_limit=0,
                        preload=["mfnormal.cli.worker"], preload_argv=["--quiet"])


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
        info = self.client.run(_worker_info)
        for address, item in info.items():
            problem = item["problem"] and f"worker {address}: {item['problem']}"
            problem = problem or _mismatch(item["versions"], self.env.versions, f"worker {address}")
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
            return self.client.submit(_files, files, key=f"mfnormal-files-{digest}", pure=False)

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
        from mfnormal.cli.rendering import weighted_mean

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

    def bsdf_checks(self, methods, samples: int, repeats: int):
        """Submit :func:`mfnormal.report.bsdf_checks.bsdf_checks` of each method; returns a
        function that collects them in order."""
        futures = [self._submit(bsdf_checks_job, m, samples, repeats) for m in methods]
        return lambda: list(self._in_order(futures))
