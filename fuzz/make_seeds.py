#!/usr/bin/env python3
"""Builds the seed corpora of the fuzz targets (seeds/<target>/) and the fixed
KITTI sequence of the KITTI targets (kitti-base/) from the project's own valid
files: the KITTI data folder (first 20 frames of each sequence), parameter
files, checkpoints and reports under results/ and the test fixtures, and small
datasets in the format the dataset writer produces (seeds/dataset-dirs/, each
written by `Dataset::write` in the round-trip test when SSM_FUZZ_SEED_DIR is
set). Run from fuzz/: python3 make_seeds.py"""
import glob, os, shutil, hashlib

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
KITTI = "/work/shared/data/kitti-tracking"
FRAMES = 20
HERE = os.path.dirname(os.path.abspath(__file__))


def put(target, data):
    d = os.path.join(HERE, "seeds", target)
    os.makedirs(d, exist_ok=True)
    name = hashlib.sha1(data).hexdigest()[:16]
    with open(os.path.join(d, name), "wb") as f:
        f.write(data)


def frames_lt(text, sep):
    out = []
    for line in text.splitlines(True):
        f = line.split(sep)[0].strip() if sep else (line.split() or ["x"])[0]
        if f.isdigit() and int(f) < FRAMES:
            out.append(line)
    return "".join(out)


def kitti_files(seq):
    s = f"{seq:04d}.txt"
    read = lambda p: open(os.path.join(KITTI, p, s)).read()
    labels = frames_lt(read("label_02"), None)
    dets = frames_lt(read("det_pointrcnn/Car"), ",")
    poses = "".join(read("ego_pose_orbslam3").splitlines(True)[:FRAMES])
    calib = read("calib")
    return [labels, dets, poses, calib]


seqs = sorted(int(os.path.basename(p)[:4]) for p in glob.glob(os.path.join(KITTI, "label_02", "*.txt")))
names = ["label_02", "det_pointrcnn/Car", "ego_pose_orbslam3", "calib"]
for i, text in enumerate(kitti_files(0)):
    p = os.path.join(HERE, "kitti-base", names[i], "0000.txt")
    os.makedirs(os.path.dirname(p), exist_ok=True)
    open(p, "w").write(text)
targets = ["kitti_labels", "kitti_detections", "kitti_poses", "kitti_calib"]
for seq in seqs:
    for t, text in zip(targets, kitti_files(seq)):
        put(t, text.encode())

# Parameter files and checkpoints: a few of each kind of run.
params = sorted(glob.glob(os.path.join(ROOT, "results", "**", "params.bin"), recursive=True))
ckpts = sorted(glob.glob(os.path.join(ROOT, "results", "**", "checkpoint.bin"), recursive=True))
ckpts += sorted(glob.glob(os.path.join(ROOT, "ssm", "tests", "fixtures", "checkpoint-v*.bin")))
def spread(paths, n):
    by_size = {}
    for p in paths:
        by_size.setdefault(os.path.getsize(p), p)
    ps = sorted(by_size.values(), key=os.path.getsize)
    step = max(1, len(ps) // n)
    return ps[::step][:n]
for p in spread(params, 8):
    raw = open(p, "rb").read()
    put("params", b"\x00" + raw)          # as it is
    put("params", b"\x01" + raw[20:])     # payload behind a rebuilt header
for p in spread(ckpts, 6) + sorted(glob.glob(os.path.join(ROOT, "ssm", "tests", "fixtures", "checkpoint-v*.bin"))):
    raw = open(p, "rb").read()
    version = int.from_bytes(raw[8:12], "little")
    top = {2: 0x40, 3: 0x80}.get(version, 0)
    put("checkpoint", bytes([top]) + raw)
    put("checkpoint", bytes([top | 1]) + raw[20:])

# Reports: one per results folder that has them, smallest first.
reports = sorted(glob.glob(os.path.join(ROOT, "results", "**", "report.json"), recursive=True))
seen = set()
for p in sorted(reports, key=os.path.getsize):
    top = os.path.relpath(p, ROOT).split(os.sep)[1]
    if top in seen or len(seen) >= 8:
        continue
    seen.add(top)
    put("report", open(p, "rb").read())

# Datasets: each folder written by the dataset writer, as one input.
FILES = ["meta.json", "av.csv", "objects.csv", "points.csv", "boxes.csv", "states.csv", "actions.csv"]
for d in sorted(glob.glob(os.path.join(HERE, "seeds", "dataset-dirs", "*"))):
    parts = []
    for f in FILES:
        p = os.path.join(d, f)
        parts.append(open(p, "rb").read() if os.path.exists(p) else b"")
    put("dataset", b"\x00".join(parts))
print("seeds:", {t: len(os.listdir(os.path.join(HERE, "seeds", t))) for t in os.listdir(os.path.join(HERE, "seeds")) if t != "dataset-dirs"})
