"""The numba kernels compiled ahead of time (estimation/aot.py) and their JIT fallback.

The byte-for-byte comparisons with liboctomap run on both (the ``kernel_backend`` fixture in
tests/test_octree.py and tests/test_octree_semantic.py); here: the argument types are
matched as numba types them, a missing signature, a stale module or another CPU falls back to
the JIT, and a whole ``octofactor map`` process needs neither numba nor GTSAM.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from estimation import aot

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _values():
    a = np.arange(24, dtype=np.float32).reshape(4, 6)
    ro = np.arange(5, dtype=np.uint8)
    ro.flags.writeable = False
    unaligned = np.frombuffer(b"\0" + bytes(8 * 4), dtype=np.uint8)[1:].view(np.float64)
    return [a, a[:, ::2], a.T, a[0], a[:, 0], np.zeros((0, 3), np.int64), ro,
            np.zeros(3, np.uint16), np.zeros((2, 2, 2), np.int32), np.array(1.5),
            unaligned, 3, 2.5, True, False, np.float32(1.5), np.float64(2.0), np.int64(7),
            np.int32(7), np.uint8(3), np.uint64(5), np.bool_(True)]


def test_arg_key_is_the_numba_type():
    """The key a call is dispatched by names exactly the type numba.typeof gives."""
    import numba

    for value in _values():
        key = aot.arg_key(value)
        assert key != "?"
        assert aot._numba_type(key) == numba.typeof(value), (key, numba.typeof(value))
    for value in (None, "x", np.zeros(2, object), np.zeros(2, ">f4"), [1, 2], 1j,
                  np.ma.masked_array(np.zeros(2))):
        assert aot.arg_key(value) == "?"


def test_the_map_kernels_are_compiled_and_called():
    ks = aot.kernels("mapping._kernels")
    assert ks.compiled is not None, "python -m estimation.aot build"
    assert ks.compiled.__name__ == aot.aot_module_name("mapping._kernels")
    codes = np.array([5, 9], np.uint64)
    before = ks.jit_calls
    assert ks.codes_to_keys(codes).tolist() == aot.kernels(
        "mapping._kernels").jit_module().codes_to_keys(codes).tolist()
    assert ks.jit_calls == before


def test_a_call_without_a_compiled_signature_goes_to_the_jit():
    ks = aot.kernels("mapping._kernels")
    keys = np.arange(30, dtype=np.int64).reshape(10, 3) + 32768
    strided = keys.astype(np.uint16)[::2]  # no compiled signature: layout 'A'
    assert aot.arg_key(strided) == "u2:2A"
    before = ks.jit_calls
    out = ks.keys_to_codes(strided)
    assert ks.jit_calls == before + 1
    assert out.tolist() == ks.keys_to_codes(np.ascontiguousarray(strided)).tolist()


def test_a_stale_module_or_another_cpu_is_not_loaded(monkeypatch, tmp_path):
    name = aot.aot_module_name("mapping._kernels")
    # another CPU (its instruction sets) names another module: none is built, the JIT runs
    monkeypatch.setattr(aot, "_cpu_id", lambda: b"another machine")
    assert aot.aot_module_name("mapping._kernels") != name
    ks = aot.Kernels("mapping._kernels")
    assert ks.compiled is None
    codes = np.array([5, 9], np.uint64)
    assert ks.codes_to_keys is ks.jit_module().codes_to_keys  # the dispatcher itself
    assert ks.codes_to_keys(codes).shape == (2, 3)
    monkeypatch.undo()
    # an edited kernel source names another module too
    source = aot._source_path("mapping._kernels")
    edited = tmp_path / source.name
    edited.write_bytes(source.read_bytes() + b"\n# edited\n")
    shutil.copy(aot.table_path("mapping._kernels"), tmp_path / (source.stem + ".aot.json"))
    monkeypatch.setattr(aot, "_source_path", lambda module_name: edited)
    assert aot.aot_module_name("mapping._kernels") != name


def _run_map(graph, out, env_extra):
    code = ("import sys\nfrom pipelines.cli import main\n"
            f"rc = main(['map', {str(graph)!r}, '-r', '0.1', '-q', '-o', {str(out)!r}])\n"
            "print(' '.join(m for m in ('numba', 'gtsam', 'scipy', 'open3d') "
            "if m in sys.modules))\nsys.exit(rc)\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([REPO, os.environ.get("PYTHONPATH", "")]))
    env.update(env_extra)
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          check=True)
    return done.stdout.split()


@pytest.mark.reference
def test_whole_map_process_needs_neither_numba_nor_gtsam(shared_data, tmp_path):
    """`octofactor map G.graph` as a fresh process: graph2tree's bytes, and with the compiled
    kernels no numba, GTSAM or SciPy import; OCTOFACTOR_JIT=1 gives the same bytes on numba."""
    graph = shared_data / "octomap" / "spherical_scan.graph"
    ref = tmp_path / "ref.bt"
    subprocess.run(["graph2tree", "-i", str(graph), "-o", str(ref), "-res", "0.1"], check=True,
                   capture_output=True)
    if os.environ.get("OCTOFACTOR_JIT", "") in ("", "0"):
        assert _run_map(graph, tmp_path / "aot.bt", {}) == []
        assert (tmp_path / "aot.bt").read_bytes() == ref.read_bytes()
    assert "numba" in _run_map(graph, tmp_path / "jit.bt", {"OCTOFACTOR_JIT": "1"})
    assert (tmp_path / "jit.bt").read_bytes() == ref.read_bytes()


def test_registration_is_the_same_on_compiled_and_jit_kernels():
    """The registration kernels (issue 14's first call) compiled ahead of time give the same
    estimate and covariance, bit for bit, as numba's JIT, and every call found its signature."""
    from estimation.registration import Registration, RegistrationConfig

    rng = np.random.default_rng(0)
    n = 3000
    pts = np.c_[rng.uniform(0, 4, n), rng.uniform(0, 4, n), np.zeros(n)]
    pts[: n // 2, 2] = pts[: n // 2, 0] * 0.3
    pts[n // 4: n // 2, 2] += np.sin(pts[n // 4: n // 2, 1])
    tgt = pts + rng.normal(0, 0.005, pts.shape)
    src = pts[rng.permutation(n)] + rng.normal(0, 0.005, pts.shape)
    ks = aot.kernels("estimation.registration._kernels")
    assert ks.compiled is not None, "python -m estimation.aot build"
    before = ks.jit_calls
    compiled = Registration(src, tgt, RegistrationConfig()).run()
    assert ks.jit_calls == before
    ks.jit_only = True
    try:
        jit = Registration(src, tgt, RegistrationConfig()).run()
    finally:
        ks.jit_only = False
    assert compiled.converged and compiled.iterations == jit.iterations
    assert np.array_equal(compiled.T, jit.T)
    assert np.array_equal(compiled.covariance, jit.covariance)
