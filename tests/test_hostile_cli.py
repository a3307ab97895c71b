"""The hostile cases of issue 16, each run as a whole ``octofactor`` process.

Every case runs under a 4 GB address-space cap (RLIMIT_AS) and a 60 s timeout and must end
with exit status 2 and exactly one line on stderr that names the file or the option, with no
traceback, no warning before it and nothing on stdout (Open3D/RPly noise). Cases run two at
a time. After all of them no temporary file (``.<name>.octofactor-<pid>.tmp``) is left and
no output of a failed case exists.
"""
from __future__ import annotations

import os
import resource
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import hostile_files as hf
import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
MEMORY_CAP = 4 << 30
TIMEOUT_S = 60
LONG = "n" * 300  # a file name over 255 bytes
BAD_NAME = os.fsdecode(b"\xff")  # a file name that is not UTF-8 (GTSAM and Open3D need it)


def _limit_memory():
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP))


def run_cli(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """Run ``python -m pipelines ARGS`` with the memory cap and the timeout."""
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT), PYTHONWARNINGS="default")
    env.pop("OCTOFACTOR_TRACEBACK", None)
    return subprocess.run([sys.executable, "-m", "pipelines", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, errors="replace",
                          timeout=TIMEOUT_S, preexec_fn=_limit_memory)


def _write_files(d: Path) -> None:
    """Every hostile file of the table, in ``d``."""
    (d / "ok.ply").write_bytes(hf.ply_bytes(60))
    (d / "ok2.ply").write_bytes(hf.ply_bytes(60))
    # more distinct label values than the class limit (a 2e9 label value alone is a class
    # like any other: tests/test_semantic_labels.py)
    (d / "labels1100.ply").write_bytes(hf.ply_bytes(1100, labels=np.arange(1100) * 1_000_000))
    (d / "claims_more.ply").write_bytes(hf.ply_bytes(30, claimed=40))
    (d / "claims_fewer.ply").write_bytes(hf.ply_bytes(60, claimed=50))
    (d / "ascii_fewer.ply").write_bytes(hf.ply_bytes(60, ascii=True, claimed=50))
    for name, count in (("claims_2e31", 2**31), ("claims_2e40", 2**40), ("claims_neg", -5)):
        (d / f"{name}.ply").write_bytes(hf.ply_bytes(30, claimed=count))
    (d / "truncated.ply").write_bytes(hf.ply_bytes(60)[:-100])
    t = np.linspace(0.0, 1.0, 60)
    line = hf.ply_bytes(60)
    header_end = line.index(b"end_header\n") + 11
    rows = np.frombuffer(line[header_end:], dtype=[("xyz", "<f4", (3,)), ("label", "<i4")]).copy()
    rows["xyz"] = np.c_[t, 2 * t, 3 * t]
    (d / "collinear.ply").write_bytes(line[:header_end] + rows.tobytes())

    bt, ot, sem = (hf.octree_bytes(k) for k in ("bt", "ot", "sem"))
    (d / "ok.bt").write_bytes(bt)
    (d / "size0.bt").write_bytes(hf.header_with(bt, b"size", b"0"))
    (d / "size0.ot").write_bytes(hf.header_with(ot, b"size", b"0"))
    (d / "foo.bt").write_bytes(hf.header_with(bt, b"id", b"Foo"))
    (d / "semid.bt").write_bytes(hf.header_with(bt, b"id", b"SemanticOcTree"))
    (d / "res1e300.ot").write_bytes(hf.header_with(ot, b"res", b"1e300"))
    start = hf.ot_payload_start(ot)
    for name, value in (("nan", np.nan), ("inf", np.inf)):
        data = bytearray(ot)
        data[start + 5 * 3:start + 5 * 3 + 4] = np.float32(value).tobytes()
        (d / f"{name}.ot").write_bytes(bytes(data))
    sem_at = hf.semantic_section(sem)
    n_classes, n_vox = np.frombuffer(sem, "<u4", 1, sem_at + 4)[0], \
        np.frombuffer(sem, "<u8", 1, sem_at + 8)[0]
    data = bytearray(sem)
    data[sem_at + 8:sem_at + 16] = np.uint64(0).tobytes()
    (d / "sem_vox0.ot").write_bytes(bytes(data))
    data = bytearray(sem)
    data[sem_at + 4:sem_at + 8] = np.uint32(n_classes - 1).tobytes()
    (d / "sem_cls2.ot").write_bytes(bytes(data))
    data = bytearray(sem)
    ev_at = sem_at + 16 + 6 * int(n_vox)
    data[ev_at:ev_at + 4] = np.float32(np.nan).tobytes()
    (d / "sem_nan.ot").write_bytes(bytes(data))

    ok_g2o = hf.g2o_text()
    (d / "ok.g2o").write_text(ok_g2o)
    (d / "garbage.g2o").write_bytes(ok_g2o.encode() + b"\x00\x01\xfe\xff binary garbage\n")
    (d / "selfloop.g2o").write_text(hf.g2o_text(
        edge=f"EDGE_SE3:QUAT 1 1 1 0 0 0 0 0 1 {hf.IDENTITY_INFO}"))
    (d / "huge.g2o").write_text(ok_g2o.replace("VERTEX_SE3:QUAT 2 2 0.1",
                                               "VERTEX_SE3:QUAT 2 1e300 0.1"))
    (d / "id2e56.g2o").write_text(ok_g2o.replace("VERTEX_SE3:QUAT 2 ", f"VERTEX_SE3:QUAT {2**56} "))
    tiny = hf.IDENTITY_INFO.replace("1 ", "1e-320 ", 1)
    (d / "tinyinfo.g2o").write_text(hf.g2o_text(
        edge=f"EDGE_SE3:QUAT 1 2 1 0.1 0 0 0 0 1 {tiny}"))
    (d / (BAD_NAME + ".g2o")).write_text(ok_g2o)
    (d / (BAD_NAME + ".ply")).write_bytes(hf.ply_bytes(60))
    (d / "deep.g2o").write_text(ok_g2o)
    (d / "deep.g2o.json").write_text("[" * 200000 + "]" * 200000)
    (d / "selfloop.graph").write_bytes(hf.scan_graph_bytes(self_loop=True))
    (d / "nanpoint.graph").write_bytes(hf.scan_graph_bytes(nan_point=True))
    (d / "empty.graph").write_bytes(b"")
    (d / "latin1.txt").write_bytes(b"# caf\xe9\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    (d / "clouds").mkdir()
    (d / "clouds" / "0.ply").write_bytes(hf.ply_bytes(30, claimed=40))
    (d / "pcd").mkdir()
    (d / "pcd" / "0.pcd").write_text(
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2000000000\n"
        "HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2000000000\nDATA ascii\n1 2 3\n4 5 6\n")

    (d / "ok.png").write_bytes(hf.png_bytes(64, 48))
    (d / "img1.png").write_bytes(hf.png_bytes(1, 1))
    (d / "huge.png").write_bytes(hf.png_claiming(60000, 60000))
    png = hf.png_bytes(64, 48)
    (d / "truncated.png").write_bytes(png[:len(png) // 2])
    import cv2

    ok, jpg = cv2.imencode(".jpg", np.full((48, 64, 3), 128, np.uint8))
    jpg = jpg.tobytes()
    (d / "garbage.jpg").write_bytes(jpg[:200] + b"\0" * 300 + jpg[500:])
    (d / "garbage.tif").write_bytes(b"II*\x00" + b"\xff" * 100)
    (d / "list.ply").write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        b"property float z\nproperty list uchar int label\nend_header\n0 0 0 1 0\n1 1 1 1 1\n")
    (d / "nan.ply").write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        b"property float z\nproperty int label\nend_header\n0 0 0 0\n1 1 1 1\nnan 2 2 0\n")
    (d / "afile").write_text("an existing file\n")
    (d / "target.json").write_text("{}\n")
    os.symlink("target.json", d / "link.json")
    (d / "vout").mkdir()
    os.symlink("../target.json", d / "vout" / "report.json")
    os.mkfifo(d / "fifo.g2o")
    hf.write_sequence(d / "seq")
    hf.write_sequence(d / "seq_broken", n_frames=4, broken=(0, 1, 2))


# (case id, arguments, text the one stderr line must contain). "{d}" is the files' folder.
CASES = [
    # simulate corridor: NaN crashed numba; no upper bounds
    ("corridor-width-nan", "simulate corridor -o {d}/c --length 3 --width nan", "--width"),
    ("corridor-length-inf", "simulate corridor -o {d}/c --length inf", "--length"),
    ("corridor-length-nan", "simulate corridor -o {d}/c --length nan", "--length"),
    ("corridor-length-1e5", "simulate corridor -o {d}/c --length 1e5", "--length"),
    ("corridor-period-1e-6", "simulate corridor -o {d}/c --period 1e-6", "--period"),
    ("corridor-period-nan", "simulate corridor -o {d}/c --period nan", "--period"),
    ("corridor-speed-nan", "simulate corridor -o {d}/c --speed nan", "--speed"),
    ("corridor-clutter-1e6", "simulate corridor -o {d}/c --clutter 1000000", "--clutter"),
    ("corridor-seed-negative", "simulate corridor -o {d}/c --seed -1", "--seed"),
    ("room-focal-negative", "simulate room -o {d}/r --focal -100", "--focal"),
    # semantic clouds: one-hot over 1100 label values; lying PLY headers
    ("register-labels-1100", "register {d}/labels1100.ply {d}/ok.ply -o {d}/o1.json",
     "labels1100.ply"),
    ("calibrate-labels-1100", "calibrate {d}/ok.ply {d}/labels1100.ply -o {d}/o2.json",
     "labels1100.ply"),
    ("register-claims-fewer", "register {d}/claims_fewer.ply {d}/ok.ply -o {d}/o3.json",
     "claims_fewer.ply"),
    ("register-ascii-claims-fewer", "register {d}/ascii_fewer.ply {d}/ok.ply -o {d}/o4.json",
     "ascii_fewer.ply"),
    ("register-claims-2e31", "register {d}/claims_2e31.ply {d}/ok.ply -o {d}/o5.json",
     "claims_2e31.ply"),
    ("register-claims-2e40", "register {d}/claims_2e40.ply {d}/ok.ply -o {d}/o6.json",
     "claims_2e40.ply"),
    ("register-claims-negative", "register {d}/claims_neg.ply {d}/ok.ply -o {d}/o7.json",
     "claims_neg.ply"),
    ("register-truncated", "register {d}/truncated.ply {d}/ok.ply -o {d}/o8.json",
     "truncated.ply"),
    # `map G.graph` maps the file and checks each node's points on the insertion threads
    ("map-graph-nan-point", "map {d}/nanpoint.graph -o {d}/o31.bt",
     "nanpoint.graph (byte 220): node #1 point 2"),
    ("map-graph-empty", "map {d}/empty.graph -o {d}/o32.bt", "empty.graph"),
    ("map-graph-self-loop", "map {d}/selfloop.graph -o {d}/o33.bt", "selfloop.graph"),
    ("map-clouds-claims-more", "map {d}/ok.g2o --clouds {d}/clouds -o {d}/o9.bt", "0.ply"),
    ("map-clouds-pcd-claims-2e9", "map {d}/ok.g2o --clouds {d}/pcd -o {d}/o28.bt", "0.pcd"),
    # octree files
    ("octree-info-dev-zero", "octree info /dev/zero", "/dev/zero"),
    ("octree-info-size0-bt", "octree info {d}/size0.bt", "size0.bt"),
    ("octree-convert-size0-bt", "octree convert {d}/size0.bt -o {d}/o10.bt", "size0.bt"),
    ("octree-info-size0-ot", "octree info {d}/size0.ot", "size0.ot"),
    ("octree-info-semantic-0-voxels", "octree info {d}/sem_vox0.ot", "sem_vox0.ot"),
    ("octree-info-semantic-classes-3-2", "octree info {d}/sem_cls2.ot", "sem_cls2.ot"),
    ("octree-info-semantic-nan", "octree info {d}/sem_nan.ot", "sem_nan.ot"),
    ("octree-convert-nan-log-odds", "octree convert {d}/nan.ot -o {d}/o11.ot", "nan.ot"),
    ("octree-export-inf-log-odds", "octree export {d}/inf.ot -o {d}/o12.ply", "inf.ot"),
    ("octree-export-res-1e300", "octree export {d}/res1e300.ot -o {d}/o13.ply", "res1e300.ot"),
    ("octree-info-unknown-bt-id", "octree info {d}/foo.bt", "foo.bt"),
    ("octree-info-semantic-bt-id", "octree info {d}/semid.bt", "semid.bt"),
    # pose graphs
    ("graph-g2o-garbage", "graph info {d}/garbage.g2o", "garbage.g2o:6"),
    ("graph-g2o-self-loop", "graph info {d}/selfloop.g2o", "selfloop.g2o:5"),
    ("graph-g2o-vertex-1e300", "graph optimize {d}/huge.g2o -o {d}/o14.g2o", "huge.g2o:3"),
    ("graph-g2o-id-2e56", "graph info {d}/id2e56.g2o", "id2e56.g2o:3"),
    ("graph-g2o-info-1e-320", "graph info {d}/tinyinfo.g2o", "tinyinfo.g2o:5"),
    ("graph-sidecar-nested-json", "graph info {d}/deep.g2o", "deep.g2o.json"),
    ("graph-graph-self-loop", "graph info {d}/selfloop.graph", "selfloop.graph"),
    ("graph-fifo", "graph info {d}/fifo.g2o", "fifo.g2o"),
    ("graph-max-iterations", "graph optimize {d}/ok.g2o -o {d}/o15.g2o --max-iterations -1",
     "--max-iterations"),
    # file names over 255 bytes, in and out
    ("graph-long-name", "graph info {d}/" + LONG + ".g2o", "file name too long"),
    ("octree-long-name", "octree info {d}/" + LONG + ".bt", "file name too long"),
    ("register-long-name", "register {d}/" + LONG + ".ply {d}/ok.ply -o {d}/o16.json",
     "file name too long"),
    ("graph-convert-long-output", "graph convert {d}/ok.g2o -o {d}/" + LONG + ".g2o",
     LONG + ".g2o"),
    ("graph-non-utf8-name", "graph info {d}/" + BAD_NAME + ".g2o", "not UTF-8"),
    ("register-non-utf8-name", "register {d}/" + BAD_NAME + ".ply {d}/ok.ply -o {d}/o27.json",
     "not UTF-8"),
    ("export-non-utf8-output", "octree export {d}/ok.bt -o {d}/" + BAD_NAME + ".ply",
     "not UTF-8"),
    ("graph-convert-missing-folder", "graph convert {d}/ok.g2o -o {d}/nofolder/x.g2o", "nofolder"),
    # transform files that are not UTF-8
    ("register-init-latin1", "register {d}/ok.ply {d}/ok2.ply -o {d}/o17.json "
     "--init {d}/latin1.txt", "latin1.txt"),
    ("register-gt-latin1", "register {d}/ok.ply {d}/ok2.ply -o {d}/o18.json "
     "--gt {d}/latin1.txt", "latin1.txt"),
    # registration options
    ("register-alpha-0", "register {d}/ok.ply {d}/ok2.ply -o {d}/o19.json --alpha 0",
     "--alpha"),
    ("register-alpha-nan", "register {d}/ok.ply {d}/ok2.ply -o {d}/o20.json --alpha nan",
     "--alpha"),
    ("register-max-corr-nan", "register {d}/ok.ply {d}/ok2.ply -o {d}/o21.json --max-corr nan",
     "--max-corr"),
    ("register-initial-corr-nan", "register {d}/ok.ply {d}/ok2.ply -o {d}/o22.json "
     "--initial-corr nan", "--initial-corr"),
    # outputs that are special files or links
    ("register-output-dev-null", "register {d}/ok.ply {d}/ok2.ply -o /dev/null", "/dev/null"),
    ("register-output-symlink", "register {d}/ok.ply {d}/ok2.ply -o {d}/link.json",
     "link.json"),
    # vanishing points
    ("vp-intrinsics-1e300", "vp {d}/ok.png --intrinsics 1e300,1e300,32,24", "--intrinsics"),
    ("vp-image-1x1", "vp {d}/img1.png --intrinsics 525,525,0,0", "img1.png"),
    ("vp-png-60000", "vp {d}/huge.png --intrinsics 525,525,0,0", "huge.png"),
    ("vp-truncated-png", "vp {d}/truncated.png --intrinsics 525,525,32,24", "truncated.png"),
    ("vp-corrupt-jpeg", "vp {d}/garbage.jpg --intrinsics 525,525,32,24", "garbage.jpg"),
    ("vp-corrupt-tiff", "vp {d}/garbage.tif --intrinsics 525,525,32,24", "garbage.tif"),
    ("register-list-label", "register {d}/list.ply {d}/ok.ply -o {d}/o25.json", "list.ply"),
    ("register-nan-point", "register {d}/nan.ply {d}/ok.ply -o {d}/o26.json --method gicp",
     "nan.ply"),
    ("vp-plot-existing-file", "vp {d}/ok.png --intrinsics 525,525,32,24 -o {d}/afile",
     "afile"),
    # vpslam
    ("vpslam-intrinsics-inf", "vpslam {d}/seq -o {d}/v1 --intrinsics 525,525,inf,239.5",
     "--intrinsics"),
    ("vpslam-depth-scale-inf", "vpslam {d}/seq -o {d}/v2 --depth-scale inf", "--depth-scale"),
    ("vpslam-output-existing-file", "vpslam {d}/seq -o {d}/afile", "afile"),
    ("vpslam-output-file-symlink", "vpslam {d}/seq -o {d}/vout --quiet", "report.json"),
    ("vpslam-most-frames-unreadable", "vpslam {d}/seq_broken -o {d}/v3 --no-map --quiet",
     "seq_broken"),
    # other options
    ("map-resolution-nan", "map {d}/ok.g2o --clouds {d}/clouds -o {d}/o23.bt -r nan",
     "--resolution"),
    ("octree-export-height-nan", "octree export {d}/ok.bt -o {d}/o24.png --height nan",
     "--height"),
    ("eval-dev-zero", "eval /dev/zero {d}/ok.g2o", "/dev/zero"),
]


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    d = tmp_path_factory.mktemp("hostile")
    _write_files(d)

    def one(case):
        name, args, _ = case
        try:
            return name, run_cli(args.format(d=d).split(), cwd=d)
        except subprocess.TimeoutExpired:
            return name, None

    with ThreadPoolExecutor(max_workers=2) as pool:
        done = dict(pool.map(one, CASES))
    return d, done


@pytest.mark.parametrize("name,args,expected", CASES, ids=[c[0] for c in CASES])
def test_hostile_case_is_one_line_and_exit_2(results, name, args, expected):
    d, done = results
    proc = done[name]
    assert proc is not None, f"timed out after {TIMEOUT_S} s"
    lines = proc.stderr.splitlines()
    if name.startswith("vpslam"):  # vpslam names each skipped frame first, by design
        lines = [ln for ln in lines if not ln.startswith("vpslam: skipped frame ")]
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert "Traceback" not in proc.stderr
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("octofactor"), lines[0]
    assert expected in lines[0], lines[0]
    assert ".octofactor-" not in lines[0], "the message names a temporary file"
    assert proc.stdout == "", proc.stdout


def test_failed_cases_leave_no_output_and_no_temporary(results):
    d, _ = results
    names = [p.name for p in d.rglob("*")]
    assert not [n for n in names if ".octofactor-" in n]
    assert not [n for n in names if n.startswith("o") and n[1:2].isdigit()]
    assert (d / "target.json").read_text() == "{}\n" and (d / "link.json").is_symlink()
    assert (d / "afile").read_text() == "an existing file\n"
    assert Path("/dev/null").is_char_device()


def test_degenerate_clouds_are_not_converged(tmp_path):
    """Collinear clouds: converged=False with 'degenerate geometry', exit 1, no warnings."""
    _write_files(tmp_path)
    proc = run_cli(["register", "collinear.ply", "collinear.ply", "-o", "r.json"], tmp_path)
    assert proc.returncode == 1, proc.stderr
    assert "degenerate geometry" in proc.stdout
    assert "warning" not in proc.stderr.lower(), proc.stderr


def test_export_leaves_no_visible_temporary(tmp_path):
    """octree export -o x.ply renders through a hidden temporary beside x.ply."""
    (tmp_path / "map.bt").write_bytes(hf.octree_bytes("bt"))
    proc = run_cli(["octree", "export", "map.bt", "-o", "x.ply"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.bt", "x.ply"]
