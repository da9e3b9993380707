"""``mfnormal render|compare --cluster``: rendering on a Dask.distributed cluster (mfnormal.render.cluster).

The cluster is a ``LocalCluster`` of two worker processes of one thread each on this
machine, shared by the tests of this module (its address is what ``--cluster ADDRESS``
takes); ``compare`` starts its own with ``local:2``, and the tests that take a cluster
down start their own. Skipped without the extra
(``pip install 'mfnormal[cluster]'``; ``scripts/setup.sh --test`` installs it).

Tolerances: a cluster render and the same chunks rendered here in sequence are
merged by the same accumulator in the same order, so they differ only where one
``mi.render`` sums its film's samples in another order (other thread counts):
|Δ| ≤ 1e-6 on pixel values of order 1 (16 float32 ulps; measured: 6e-8). Against a
render with other seeds the image mean is compared within 4.5 standard errors of
the per-pixel differences (the seeds are fixed: it passes or fails the same way
every run).
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

import mitsuba as mi  # noqa: E402

from cli_checks import assert_error_line, assert_one_line_error  # noqa: E402
from helpers import write_maps, xml_plugin, xml_scene  # noqa: E402
from mfnormal.cli import commands as cli  # noqa: E402
from mfnormal.render.bundle import xml_bundle  # noqa: E402
from mfnormal.render.passes import average_passes, film_image, schedule  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TOL = 1e-6
SHAPES = ('<shape type="sphere">' + xml_plugin() + '</shape>'
          '<shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/>'
          '<translate y="-1"/></transform><bsdf type="diffuse"/></shape>')


@pytest.fixture(scope="module")
def cluster():
    import logging

    c = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                 dashboard_address=":0", silence_logs=logging.ERROR)
    client = distributed.Client(c)
    yield c, client
    client.close()
    c.close()


def _scene(folder: Path, spp=16, width=32, height=24) -> Path:
    write_maps(folder)
    path = folder / "scene.xml"
    path.write_text(xml_scene(SHAPES, {"nm": "normalmap.png", "model": "faithful"}, spp=str(spp),
                              width=str(width), height=str(height)))
    return path


def _exr(path) -> np.ndarray:
    return np.array(mi.Bitmap(str(path)), dtype=np.float64)


def _sequential(scene_path, spp: int, chunks: int, seed: int) -> np.ndarray:
    """The chunks of a cluster render (``--chunks``, ``--seed``), rendered here one after another."""
    scene = mi.load_file(str(scene_path))
    w, h = scene.sensors()[0].film().crop_size()
    return film_image(average_passes(scene, schedule(spp, int(w) * int(h), chunks, seed)))[..., :3]


def _outputs(folder: Path) -> list:
    """The render's outputs in ``folder`` (``out.exr``, ``out.png``), and temporary files."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(("out", ".")))


def _cli(argv, capsys):
    rc = cli.main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


# -- Arguments -----------------------------------------------------------------------------


@pytest.mark.parametrize("value", ["local", "local:0", "local:two", "local:-1", "scheduler",
                                   "http://host:8786", "tcp://host", "host:99999", "tcp://a b:1"])
def test_bad_cluster_values_are_one_line_errors_before_any_work(tmp_path, value):
    scene = _scene(tmp_path)
    proc = subprocess.run([sys.executable, "-m", "mfnormal", "render", str(scene), "-o",
                           str(tmp_path / "out"), "--cluster", value], capture_output=True, text=True,
                          timeout=60) if value == "local" else None
    if proc is not None:            # one run as a process: the exit code and stderr as a user sees them
        assert_one_line_error(proc, "--cluster")
    rc = cli.main(["render", str(scene), "-o", str(tmp_path / "out"), "--cluster", value])
    assert rc == 2
    assert not (tmp_path / "out.exr").exists()


def test_without_the_extra_cluster_is_one_line_that_says_what_to_install(tmp_path):
    blocker = tmp_path / "blocker" / "distributed"     # the extra not installed: import distributed fails
    blocker.mkdir(parents=True)
    (blocker / "__init__.py").write_text("raise ModuleNotFoundError(\"No module named 'distributed'\")\n")
    path = [str(blocker.parent)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    proc = subprocess.run([sys.executable, "-m", "mfnormal", "render", str(_scene(tmp_path)), "-o",
                           str(tmp_path / "out"), "--cluster", "local:2"], capture_output=True, text=True,
                          env=dict(os.environ, PYTHONPATH=os.pathsep.join(path)), timeout=120)
    assert_one_line_error(proc, "--cluster needs Dask.distributed", "pip install 'mfnormal[cluster]'")
    assert proc.returncode == 2
    assert _outputs(tmp_path) == []


def test_unreachable_scheduler_is_one_line_and_writes_nothing(tmp_path, capsys):
    scene = _scene(tmp_path)
    with socket.socket() as s:          # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    rc, _, err = _cli(["render", str(scene), "-o", str(tmp_path / "out"), "--cluster",
                       f"127.0.0.1:{port}", "--cluster-timeout", "1"], capsys)
    assert rc == 2 and "cannot reach the scheduler" in err and len(err.strip().splitlines()) == 1, err
    assert time.monotonic() - t0 < 30
    assert _outputs(tmp_path) == []


def _connect_seconds(address: str, tls: tuple, timeout: float) -> tuple:
    """(seconds, error) of connecting to ``address`` as ``render --cluster`` does, in a thread
    of its own (a connection that hangs fails the test instead of holding it)."""
    from mfnormal.render.cluster import Cluster, parse_cluster
    from mfnormal.io.inputs import CLIError

    outcome = []

    def connect():
        started = time.monotonic()
        try:
            with Cluster(parse_cluster(address, tls), mi.variant(), timeout):
                outcome.append((time.monotonic() - started, None))
        except CLIError as exc:
            outcome.append((time.monotonic() - started, str(exc)))

    thread = threading.Thread(target=connect, daemon=True)
    thread.start()
    thread.join(timeout + 60)
    assert outcome, f"connecting to {address} with a timeout of {timeout:g} s still waits after a minute more"
    return outcome[0]


@pytest.mark.parametrize("scheme", ["tcp", "tls"])
def test_a_scheduler_that_never_answers_is_one_line_within_the_timeout(tmp_path, worker, scheme):
    """A listener that accepts connections and never answers (the kernel accepts them into its
    backlog): ``--cluster-timeout 2`` bounds the whole connection, Dask's handshake included,
    on tcp:// as on tls:// (a tcp:// client waited for the handshake's reply for ever): the
    command exits 2 with one line naming the address and the timeout; the connection gives up
    within the timeout and 2 s (measured: 2.0 s)."""
    scene = _scene(tmp_path)
    tls = ()
    if scheme == "tls":
        cert, key = _certificate(tmp_path)
        tls = (cert, cert, key)
    options = [x for flag, f in zip(("ca", "cert", "key"), tls) for x in (f"--cluster-tls-{flag}", f)]
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        address = f"{scheme}://127.0.0.1:{silent.getsockname()[1]}"
        result = worker.run(["render", scene, "-o", tmp_path / "out", "--cluster", address,
                             "--cluster-timeout", "2", *options], tmp_path, timeout=60)
        seconds, error = _connect_seconds(address, tls, 2.0)
    assert_error_line(result, f"--cluster {address}: cannot reach the scheduler", "within 2 s")
    assert error and "within 2 s" in error and seconds < 2 + 2, (seconds, error)
    assert _outputs(tmp_path) == []


def test_an_unsupported_protocol_is_one_line_naming_the_supported_ones(tmp_path, capsys):
    rc, _, err = _cli(["render", str(_scene(tmp_path)), "-o", str(tmp_path / "out"), "--cluster",
                       "ucx://127.0.0.1:8786"], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert "ucx:// protocol is not supported" in err and "tcp://, tls://" in err, err
    assert _outputs(tmp_path) == []


@pytest.mark.parametrize("args,needle", [
    (["--cluster", "tls://127.0.0.1:8786"], "needs certificates: --cluster-tls-ca"),
    (["--cluster", "tcp://127.0.0.1:8786", "--cluster-tls-ca", "c.pem", "--cluster-tls-cert", "c.pem"],
     "need a tls:// scheduler address"),
    (["--cluster", "tls://127.0.0.1:8786", "--cluster-tls-cert", "c.pem"], "go together"),
    (["--cluster", "tls://127.0.0.1:8786", "--cluster-tls-ca", "fifo.pem", "--cluster-tls-cert", "c.pem"],
     "--cluster-tls-ca fifo.pem is a FIFO"),
    (["--cluster", "tls://127.0.0.1:8786", "--cluster-tls-ca", "absent.pem", "--cluster-tls-cert", "c.pem"],
     "--cluster-tls-ca absent.pem: no such file"),
    (["--cluster-tls-ca", "c.pem"], "go with --cluster"),
])
def test_tls_options_are_checked_before_any_work(tmp_path, capsys, args, needle):
    scene = _scene(tmp_path)
    (tmp_path / "c.pem").write_text("not used: the arguments are refused first")
    os.mkfifo(tmp_path / "fifo.pem")
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        rc, _, err = _cli(["render", str(scene), "-o", "out", *args], capsys)
    finally:
        os.chdir(cwd)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and needle in err, err
    assert _outputs(tmp_path) == []


def test_a_tls_certificate_without_its_key_is_one_line_naming_the_option_and_the_fix(tmp_path, capsys):
    """``--cluster-tls-cert`` without ``--cluster-tls-key`` must hold the key too: a certificate
    alone (OpenSSL said "[SSL] PEM lib") or a key alone is refused before any work, naming the
    option, the file and the fix; a PEM with both is taken."""
    from mfnormal.render.cluster import parse_cluster

    cert, key = _certificate(tmp_path)
    both = tmp_path / "both.pem"
    both.write_bytes(cert.read_bytes() + key.read_bytes())
    scene = _scene(tmp_path)
    for alone in (cert, key):
        rc, _, err = _cli(["render", str(scene), "-o", str(tmp_path / "out"), "--cluster", "tls://127.0.0.1:1",
                           "--cluster-tls-ca", str(cert), "--cluster-tls-cert", str(alone)], capsys)
        assert rc == 2 and len(err.strip().splitlines()) == 1, err
        assert f"--cluster-tls-cert {alone}: no certificate with its private key" in err, err
        assert "--cluster-tls-key FILE, or a PEM file that holds both" in err and "PEM lib" not in err, err
    assert parse_cluster("tls://127.0.0.1:1", (cert, both, None)).tls == (str(cert), str(both), None)
    assert _outputs(tmp_path) == []


def test_tls_files_that_openssl_refuses_are_one_line_naming_the_option(tmp_path, capsys):
    """The CA, certificate and key files as OpenSSL reads them, before any work: a CA file with a
    key and no certificate, a key file with a certificate and no key, a certificate file with a
    key and no certificate, an encrypted key and another certificate's key were each "cannot
    reach the scheduler" with OpenSSL's words ("[SSL] PEM lib", "[X509:
    NO_CERTIFICATE_OR_CRL_FOUND]", "key values mismatch"); each is one line naming the option
    and the fix, and nothing is tried on the network."""
    import shutil

    cert, key = _certificate(tmp_path)
    (tmp_path / "other").mkdir()
    _, other = _certificate(tmp_path / "other")
    encrypted = tmp_path / "encrypted.pem"
    if shutil.which("openssl") is None:
        pytest.skip("no openssl command to encrypt a test key")
    subprocess.run(["openssl", "rsa", "-in", str(key), "-aes256", "-passout", "pass:secret", "-out",
                    str(encrypted)], check=True, capture_output=True, timeout=60)
    scene = _scene(tmp_path)
    cases = [((key, cert, key), f"--cluster-tls-ca {key}: no CA certificate in this file"),
             ((cert, cert, cert), f"--cluster-tls-key {cert}: no private key in this file"),
             ((cert, key, key), f"--cluster-tls-cert {key}: no certificate in this file"),
             ((cert, cert, encrypted), f"--cluster-tls-key {encrypted}: the key is encrypted"),
             ((cert, cert, other), f"--cluster-tls-key {other} is not the key of --cluster-tls-cert {cert}")]
    for (ca, crt, k), needle in cases:
        rc, _, err = _cli(["render", str(scene), "-o", str(tmp_path / "out"), "--cluster", "tls://127.0.0.1:1",
                           "--cluster-tls-ca", str(ca), "--cluster-tls-cert", str(crt), "--cluster-tls-key", str(k)],
                          capsys)
        assert rc == 2 and len(err.strip().splitlines()) == 1, err
        assert needle in err and "cannot reach" not in err and "PEM lib" not in err, err
    assert _outputs(tmp_path) == []


# -- Strangers -------------------------------------------------------------------------------


def _listening(pid: int) -> set:
    """(address, port, pid) of every TCP socket that process ``pid`` and its children listen on."""
    import psutil

    try:
        parent = psutil.Process(pid)
        procs = [parent, *parent.children(recursive=True)]
    except psutil.NoSuchProcess:
        return set()
    found = set()
    for proc in procs:
        try:
            found |= {(c.laddr.ip, c.laddr.port, proc.pid) for c in proc.net_connections("tcp")
                      if c.status == psutil.CONN_LISTEN}
        except psutil.NoSuchProcess:
            pass
    return found


JUNK = (b"GET /json/identity.json HTTP/1.1\r\nHost: x\r\n\r\n", b"\xff" * 64,
        bytes(range(256)) * 4)


def test_a_local_cluster_listens_on_loopback_only_and_prints_nothing_for_junk_bytes(tmp_path):
    """During a ``--cluster local:2`` render every socket of the client and its workers
    listens on loopback (Dask's dashboard would listen on every interface), and bytes that
    are not Dask's sent to each of them print nothing (Dask's comms logged a traceback per
    connection: a frame length read from junk, "Unable to allocate 6.09 EiB"). The render
    is long and ended with SIGTERM: its stderr then holds only "terminated"."""
    scene = _scene(tmp_path, spp=1 << 20, width=48, height=36)
    proc = subprocess.Popen([sys.executable, "-m", "mfnormal", "render", str(scene), "-o",
                             str(tmp_path / "out"), "--cluster", "local:2"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=str(ROOT))
    try:
        deadline, sockets = time.monotonic() + 120, set()
        while time.monotonic() < deadline and proc.poll() is None:
            sockets = _listening(proc.pid)
            if len({pid for _, _, pid in sockets}) >= 3:       # the client and both workers
                break
            time.sleep(0.2)
        assert len({pid for _, _, pid in sockets}) >= 3, (sockets, proc.poll())
        time.sleep(1.0)
        sockets = _listening(proc.pid)
        assert {ip for ip, _, _ in sockets} <= {"127.0.0.1", "::1"}, sockets
        for _, port, _ in sorted(sockets):
            for junk in JUNK:
                try:
                    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
                        s.sendall(junk)
                        time.sleep(0.05)
                except OSError:
                    pass                            # a server that hung up on the junk: fine
        time.sleep(2.0)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert err.strip() == "mfnormal: terminated", err[-3000:]
    assert proc.returncode == 143 and _outputs(tmp_path) == []


def _certificate(folder: Path) -> tuple:
    """A self-signed certificate and its key (PEM), made with the openssl command."""
    import shutil

    if shutil.which("openssl") is None:
        pytest.skip("no openssl command to make a test certificate")
    cert, key = folder / "cert.pem", folder / "key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key),
                    "-out", str(cert), "-days", "1", "-subj", "/CN=mfnormal-test"], check=True,
                   capture_output=True, timeout=60)
    return cert, key


def test_a_tls_scheduler_renders_with_certificates_from_the_options_or_dasks_configuration(
        tmp_path, capsys):
    """A scheduler and worker that take only TLS connections signed by a self-signed CA:
    ``--cluster tls://`` with ``--cluster-tls-*`` renders what the chunks rendered here
    give; so does Dask's own ``distributed.comm.tls`` configuration in their place; a
    ``tcp://`` client is refused in one line."""
    import logging

    import dask

    cert, key = _certificate(tmp_path)
    roles = {f"tls_{r}_{k}": str(f) for r in ("scheduler", "worker", "client") for k, f in (("cert", cert),
                                                                                           ("key", key))}
    security = distributed.Security(tls_ca_file=str(cert), require_encryption=True, **roles)
    scene = _scene(tmp_path)
    tls = ["--cluster-tls-ca", str(cert), "--cluster-tls-cert", str(cert), "--cluster-tls-key", str(key)]
    config = {"distributed.comm.tls.ca-file": str(cert), "distributed.comm.tls.client.cert": str(cert),
              "distributed.comm.tls.client.key": str(key)}
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, protocol="tls://",
                                  host="127.0.0.1", security=security, dashboard_address=None,
                                  silence_logs=logging.CRITICAL) as c:
        address = c.scheduler_address
        assert address.startswith("tls://")
        run = ["render", str(scene), "--chunks", "3", "--cluster", address, "--cluster-timeout", "20"]
        rc, out, err = _cli(run + ["-o", str(tmp_path / "out")] + tls, capsys)
        assert rc == 0 and "3 chunks on 1 worker(s)" in out, err
        with dask.config.set(config):
            rc, _, err = _cli(run + ["-o", str(tmp_path / "config")], capsys)
        assert rc == 0, err
        rc, _, err = _cli(["render", str(scene), "-o", str(tmp_path / "plain"), "--cluster",
                           address.replace("tls://", "tcp://"), "--cluster-timeout", "3"], capsys)
    assert rc == 2 and "cannot reach the scheduler" in err and len(err.strip().splitlines()) == 1, err
    same = _sequential(scene, 16, 3, 0)
    assert np.abs(_exr(tmp_path / "out.exr") - same).max() <= TOL
    assert np.abs(_exr(tmp_path / "config.exr") - same).max() <= TOL
    assert not (tmp_path / "plain.exr").exists()


# -- What travels ----------------------------------------------------------------------------


def test_the_bundle_holds_the_files_the_scene_names_and_nothing_else(tmp_path):
    scene = _scene(tmp_path)
    (tmp_path / "private.txt").write_text("not named by the scene")
    (tmp_path / "part.xml").write_text('<scene version="3.0.0"><shape type="obj">'
                                       '<string name="filename" value="$mesh"/></shape></scene>')
    (tmp_path / "mesh.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    text = scene.read_text().replace("</scene>", '<include filename="part.xml"/></scene>')
    text = text.replace('<default name="model"', '<default name="mesh" value="mesh.obj"/>'
                        '<default name="model"')
    bundled, params, files = xml_bundle(text, tmp_path, {"nm": "gray.png", "model": "analytic"})
    contents = {data for data in files.values()}
    assert (tmp_path / "gray.png").read_bytes() in contents          # the -D value, not the default
    assert (tmp_path / "normalmap.png").read_bytes() not in contents
    assert (tmp_path / "mesh.obj").read_bytes() in contents          # named inside the include
    assert len(files) == 3 and not any(b"not named" in d for d in files.values())
    assert "gray.png" not in bundled.replace("_gray.png", "") and params == {"model": "analytic"}
    include = next(d for k, d in files.items() if k.endswith("part.xml")).decode()
    assert next(k for k in files if k.endswith("mesh.obj")) in include


def test_the_plugins_map_strings_travel_with_the_scene(tmp_path):
    """``<string name="normalmap">`` and ``<string name="heightmap">`` name files as ``filename``
    does: both are read into the bundle and renamed in the text."""
    write_maps(tmp_path)
    text = ('<scene version="3.0.0"><bsdf type="normalmap_microfacet"><string name="normalmap" '
            'value="normalmap.png"/><bsdf type="diffuse"/></bsdf><bsdf type="normalmap_microfacet">'
            '<string name="heightmap" value="gray.png"/><bsdf type="diffuse"/></bsdf></scene>')
    bundled, _, files = xml_bundle(text, tmp_path, {})
    assert sorted(files.values()) == sorted((tmp_path / n).read_bytes() for n in ("normalmap.png", "gray.png"))
    assert all(f'value="{k}"' in bundled for k in files)


# -- Rendering ---------------------------------------------------------------------------------


def test_cluster_render_equals_its_chunks_rendered_in_sequence_and_a_local_render_within_noise(
        tmp_path, cluster, capsys):
    scene = _scene(tmp_path, spp=20)
    address = cluster[0].scheduler_address
    rc, out, err = _cli(["render", str(scene), "-o", str(tmp_path / "cl"), "--seed", "3",
                         "--chunks", "6", "--cluster", address], capsys)
    assert rc == 0, err
    assert "6 chunks on 2 worker(s)" in out
    img = _exr(tmp_path / "cl.exr")
    same = _sequential(scene, 20, 6, 3)
    assert np.abs(img - same).max() <= TOL
    assert np.abs(img - _sequential(scene, 20, 6, 4)).max() > 1e-3      # the seeds matter
    assert np.abs(img - _sequential(scene, 20, 5, 3)).max() > 1e-3      # and so does the split

    rc, _, err = _cli(["render", str(scene), "-o", str(tmp_path / "local"), "--seed", "11"], capsys)
    assert rc == 0, err
    diff = (img - _exr(tmp_path / "local.exr")).mean(axis=-1).ravel()
    z = diff.mean() / (diff.std(ddof=1) / np.sqrt(diff.size))
    assert abs(z) < 4.5, z
    assert np.abs(diff).max() > 1e-3                                    # independent samples


def test_with_shared_files_the_workers_read_the_scene_from_its_path(tmp_path, cluster, capsys):
    scene = _scene(tmp_path)
    rc, _, err = _cli(["render", str(scene), "-o", str(tmp_path / "out"), "--chunks", "3",
                       "--shared-files", "--cluster", cluster[0].scheduler_address], capsys)
    assert rc == 0, err
    assert np.abs(_exr(tmp_path / "out.exr") - _sequential(scene, 16, 3, 0)).max() <= TOL
    from mfnormal.render.bundle import scene_spec

    spec, files = scene_spec(scene, {"nm": "gray.png"}, shared=True)
    assert files == {} and spec.shared and spec.source == str(scene.resolve())
    assert spec.params == (("nm", "gray.png"),)


def test_workers_with_another_mfnormal_are_refused_with_one_line(tmp_path, capsys):
    """A worker that imports another copy of mfnormal (its source differs by one comment, so its
    version's source hash differs) is refused before any work."""
    import logging
    import shutil

    import mfnormal
    from mfnormal.render.tasks import _package_version

    scene = _scene(tmp_path)
    other = tmp_path / "other"
    shutil.copytree(Path(mfnormal.__file__).parent, other / "mfnormal",
                    ignore=shutil.ignore_patterns("__pycache__"))
    with open(other / "mfnormal" / "__init__.py", "a") as f:
        f.write("# another checkout\n")
    c = distributed.LocalCluster(n_workers=0, processes=True, dashboard_address=":0",
                                 silence_logs=logging.CRITICAL)
    client = distributed.Client(c)
    worker = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", c.scheduler_address,
                               "--nthreads", "1", "--no-nanny", "--no-dashboard"],
                              env=dict(os.environ, PYTHONPATH=str(other)), cwd=str(tmp_path),
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        client.wait_for_workers(1, timeout=60)
        rc, _, err = _cli(["render", str(scene), "-o", str(tmp_path / "out"), "--cluster",
                           c.scheduler_address], capsys)
    finally:
        worker.terminate()
        worker.wait(timeout=60)
        client.close()
        c.close()
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert f"(the client has {_package_version()})" in err and "refusing to mix" in err, err
    assert _outputs(tmp_path) == []


def _render_process(scene, out, address, *extra):
    return subprocess.Popen([sys.executable, "-m", "mfnormal", "render", str(scene), "-o", str(out),
                             "--cluster", address, *extra], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=str(ROOT))


def _processing_chunk(client, timeout=60.0):
    """The address of a worker processing a chunk of the render (waits for one)."""
    def processing(dask_scheduler):
        return [ts.processing_on.address for ts in dask_scheduler.tasks.values()
                if ts.state == "processing" and "render_chunk" in str(ts.key) and ts.processing_on]

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = client.run_on_scheduler(processing)
        if found:
            return found[0]
        time.sleep(0.05)
    raise AssertionError("no chunk was processed")


def test_a_worker_killed_mid_run_leaves_a_complete_and_correct_render(tmp_path, cluster):
    c, client = cluster
    scene = _scene(tmp_path, spp=64, width=48, height=36)
    proc = _render_process(scene, tmp_path / "out", c.scheduler_address, "--chunks", "8", "--seed", "5")
    victim = _processing_chunk(client)
    pids = client.run(os.getpid)
    assert proc.poll() is None                   # mid-run
    os.kill(pids[victim], signal.SIGKILL)
    out, err = proc.communicate(timeout=180)
    assert proc.returncode == 0, err
    assert np.abs(_exr(tmp_path / "out.exr") - _sequential(scene, 64, 8, 5)).max() <= TOL
    deadline = time.monotonic() + 60             # the nanny restarts it, for the next tests
    while time.monotonic() < deadline:
        now = client.run(os.getpid)
        if len(now) == 2 and pids[victim] not in now.values():
            break
        time.sleep(0.1)


def _own_cluster(workers: int):
    """A cluster of its own, for a test that takes it down."""
    import logging

    c = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                 dashboard_address=":0", silence_logs=logging.CRITICAL)
    return c, distributed.Client(c)


def test_a_render_whose_workers_all_leave_writes_nothing(tmp_path):
    scene = _scene(tmp_path, spp=64, width=48, height=36)
    c, client = _own_cluster(2)
    try:
        proc = _render_process(scene, tmp_path / "out", c.scheduler_address, "--chunks", "8",
                               "--cluster-timeout", "2")
        _processing_chunk(client)
        c.scale(0)                               # every worker gone for good
        try:
            out, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            raise AssertionError(f"still running 60 s after its workers left ({client.nthreads()}): "
                                 f"{err[-2000:]}") from None
    finally:
        client.close()
        c.close()
    assert proc.returncode == 2, out + err
    assert "no worker" in err and len(err.strip().splitlines()) == 1, err
    assert _outputs(tmp_path) == []


def _scheduler_process(folder: Path):
    """A Dask scheduler in a process of its own, on loopback, and its address."""
    file = folder / "scheduler.json"
    proc = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                             "--port", "0", "--no-dashboard", "--scheduler-file", str(file)],
                            cwd=str(folder), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while not file.exists() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.1)
    import json
    try:
        return proc, json.loads(file.read_text())["address"]
    except (OSError, ValueError):
        proc.kill()
        raise AssertionError("the scheduler did not start") from None


def test_a_render_whose_scheduler_is_lost_writes_nothing(tmp_path):
    """The scheduler process is killed mid-render (a crash, a lost node): the render ends with
    one line that says so. The scheduler dies at once, its worker alive: no interval without
    a worker that the client could mistake for the workers leaving (closing a LocalCluster
    stops its workers first, and under load its scheduler outlived --cluster-timeout)."""
    scene = _scene(tmp_path, spp=64, width=48, height=36)
    scheduler, address = _scheduler_process(tmp_path)
    worker = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1",
                               "--no-nanny", "--no-dashboard", "--host", "127.0.0.1"], cwd=str(tmp_path),
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    client = distributed.Client(address, timeout="60s")
    try:
        proc = _render_process(scene, tmp_path / "out", address, "--chunks", "8", "--cluster-timeout", "2")
        _processing_chunk(client)
        scheduler.kill()
        scheduler.wait(timeout=60)
        out, err = proc.communicate(timeout=120)
    finally:
        client.close(timeout=5)
        for p in (scheduler, worker):
            p.kill()
            p.wait(timeout=60)
    assert proc.returncode == 2, out + err
    assert "lost the cluster" in err and len(err.strip().splitlines()) == 1, err
    assert _outputs(tmp_path) == []


# -- compare ---------------------------------------------------------------------------------


def _report_numbers(path: Path) -> str:
    """The report's tables without their timing columns."""
    html = path.read_text()
    tables = "".join(re.findall(r"<table.*?</table>", html, flags=re.S))
    return re.sub(r"\d+\.\d s\b", "<time>", tables)


@pytest.mark.slow
def test_compare_on_a_local_cluster_gives_the_same_report(tmp_path, capsys):
    scene = _scene(tmp_path)
    args = ["compare", str(scene), "--quick", "--methods", "flat,classic,faithful,analytic"]
    rc, _, err = _cli(args + ["-o", str(tmp_path / "here")], capsys)
    assert rc == 0, err
    rc, _, err = _cli(args + ["-o", str(tmp_path / "there"), "--cluster", "local:2"], capsys)
    assert rc == 0, err
    here, there = _report_numbers(tmp_path / "here" / "report.html"), \
        _report_numbers(tmp_path / "there" / "report.html")
    assert "relMSE" in here and here == there
    for key in ("flat", "classic", "faithful", "analytic", "faithful_ref"):
        a, b = (_exr(tmp_path / d / "scene" / f"{key}.exr") for d in ("here", "there"))
        assert np.abs(a - b).max() <= TOL, key


def test_compare_on_two_local_workers_of_an_openexr_scene_ends_with_its_report(tmp_path):
    """The documented ``compare demo --cluster local:2`` (the demo's sky is an OpenEXR file) in a
    child process: on a machine of two cores it waited for ever, no CPU used (each worker's share
    was one Dr.Jit thread, with which Mitsuba's OpenEXR reader waits for a task no thread runs).
    Tiny settings: the hang came before the first pixel."""
    proc = subprocess.Popen([sys.executable, "-m", "mfnormal", "compare", "demo", "--quick", "--methods", "flat",
                             "--width", "16", "--spp", "1", "--ref-spp", "1", "-o", str(tmp_path),
                             "--cluster", "local:2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=180)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)           # the client and its workers
        proc.communicate()
        pytest.fail("compare --cluster local:2 still running after 180 s")
    assert proc.returncode == 0 and "Traceback" not in err, out + err
    assert (tmp_path / "report.html").is_file() and (tmp_path / "demo" / "flat.exr").is_file()


def test_a_worker_never_renders_with_one_dr_jit_thread():
    """With one thread (no pool thread) Mitsuba's OpenEXR reader and writer wait for ever: a
    worker's share of ``local:N`` (its cores over N) is at least two threads on any machine,
    and a worker whose own count is one is raised to two."""
    import drjit as dr

    from mfnormal.render.cluster import Cluster, parse_cluster
    from mfnormal.render.passes import MIN_THREADS
    from mfnormal.render.tasks import Env, _prepare, versions

    assert MIN_THREADS >= 2
    assert Cluster(parse_cluster(f"local:{os.cpu_count() or 1}"), mi.variant()).env.threads >= MIN_THREADS
    old = dr.thread_count()
    try:
        dr.set_thread_count(1)
        _prepare(Env(mi.variant(), versions(), None))
        assert dr.thread_count() == MIN_THREADS
        _prepare(Env(mi.variant(), versions(), 1))
        assert dr.thread_count() == MIN_THREADS
    finally:
        dr.set_thread_count(old)


def test_compare_on_a_local_cluster_shows_the_methods_that_refuse_the_scene(tmp_path, capsys):
    """The water scene on a cluster: the paper's model refuses its dielectric as it does here (no
    render, its reason in the report), the others render; exit 0."""
    args = ["compare", "water", "--quick", "--methods", "flat,faithful,analytic",
            "-o", str(tmp_path), "--cluster", "local:1"]
    rc, out, err = _cli(args, capsys)
    assert rc == 0, err
    assert re.search(r"analytic +refuses this scene", out), out
    html = (tmp_path / "report.html").read_text()
    assert "id='refused-water-analytic'" in html and "model=&#x27;analytic&#x27; only reflects" in html
    assert not (tmp_path / "water" / "analytic.exr").exists()
    assert all((tmp_path / "water" / f"{key}.exr").is_file() for key in ("flat", "faithful"))


# -- A worker's own variant (mfnormal.render.worker) -----------------------------------------------------


def _preloaded_cluster(variant: str):
    import logging

    return distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                    dashboard_address=":0", silence_logs=logging.CRITICAL,
                                    preload=["mfnormal.render.worker"], preload_argv=["--variant", variant])


def test_a_worker_started_with_a_variant_renders_its_chunks_in_it(tmp_path, capsys):
    scene = _scene(tmp_path, width=8, height=6)
    with _preloaded_cluster("scalar_rgb") as c:
        rc, out, err = _cli(["render", str(scene), "-o", str(tmp_path / "out"), "--spp", "1",
                             "--cluster", c.scheduler_address], capsys)
    assert rc == 0, err
    assert "scalar_rgb" in out and np.isfinite(_exr(tmp_path / "out.exr")).all()


def test_a_worker_that_cannot_use_its_variant_is_refused_with_one_line(tmp_path, capsys):
    import drjit as dr

    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("a CUDA device is here: the refusal is for workers without one")
    scene = _scene(tmp_path)
    with _preloaded_cluster("cuda_ad_rgb") as c:
        rc, _, err = _cli(["render", str(scene), "-o", str(tmp_path / "out"), "--cluster",
                           c.scheduler_address], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert "cannot use variant 'cuda_ad_rgb'" in err
    assert _outputs(tmp_path) == []


def test_a_gltf_bundle_holds_its_buffers_and_images_and_nothing_else(tmp_path):
    import json

    from mfnormal.render.bundle import scene_spec

    (tmp_path / "mesh.bin").write_bytes(b"\0" * 12)
    (tmp_path / "albedo map.png").write_bytes(b"png bytes")
    (tmp_path / "unrelated.png").write_bytes(b"not named")
    doc = {"asset": {"version": "2.0"}, "buffers": [{"uri": "mesh.bin", "byteLength": 12}],
           "images": [{"uri": "albedo%20map.png"}, {"uri": "data:image/png;base64,AAAA"}]}
    (tmp_path / "model.gltf").write_text(json.dumps(doc))
    spec, files = scene_spec(tmp_path / "model.gltf", {}, gltf_options={"spp": 4})
    assert sorted(files.values()) == sorted([b"\0" * 12, b"png bytes", files[spec.source]])
    bundled = json.loads(files[spec.source])
    assert [b["uri"] for b in bundled["buffers"]] == [k for k in files if k.endswith("mesh.bin")]
    assert bundled["images"][0]["uri"].endswith("albedo_map.png")
    assert bundled["images"][1]["uri"].startswith("data:") and spec.params == (("spp", 4),)
