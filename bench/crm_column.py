#!/usr/bin/env python3
"""CRM on one column of voxels: the CRM paper's update written again from the paper alone, against
mrfmap's engine on the same readings, and where the surface ends up (#33 item 4).

One ray, repeated: a camera looks along a column of voxels at a wall `--depth` metres away and
reads it `--rays` times with Gaussian noise of std `--sigma` (seeded). Every voxel starts with
the paper's uniform pdf over its occupancy (`--particles` particles). Each reading updates the
voxels by the paper's equations (cause prior from the current means, sensor cause model,
`alpha m + beta` factors), computed here with numpy in float64 and nothing of mrfmap's code.
The same readings are written as a dataset of 1 x 1 images and built by `mrfmap build --engine
crm`; the two columns of means are compared voxel by voxel, with mrfmap's two documented
departures from the paper (the likelihood cut 6 std from the reading; voxels no single reading
moves by 0.001 left unknown) done here the same way for that comparison only.

It also prints, per resolution, where the first reading's cause model peaks. Unobserved voxels
of mean mu make the cause prior fall by a factor (1 - mu) per voxel along the ray, while the
likelihood falls as exp(-x^2 / 2) in x = (distance in front of the reading) / sigma. Their
product peaks at

    delta = ln(1 / (1 - mu)) sigma^2 / r

in front of the reading (r the voxel edge): 0.69 sigma^2 / r with the paper's uniform pdfs. When
delta passes a voxel or the accuracy metric's tolerance, the surface is mapped in front of the
wall, and more so the finer the grid.

    python3 bench/crm_column.py --mrfmap target/release/mrfmap --sigma 0.13 --depth 3.6

Needs numpy. Writes its datasets under a temporary folder.
"""

import argparse
import json
import math
import os
import struct
import subprocess
import tempfile
import zlib

import numpy as np

ERFC = np.frompyfunc(math.erfc, 1, 1)


def upper(x):
    """P(N(0, 1) > x)."""
    return 0.5 * np.asarray(ERFC(np.asarray(x, dtype=float) / math.sqrt(2.0)), dtype=float)


def likelihoods(z, r, sigma, stop, cut=None):
    """Per voxel the crossed part of (0, stop] and the reading's likelihood if the surface lies
    in it (the forward model averaged over that part), and the likelihood of the final cause
    (the model averaged over one voxel past `stop`). With `cut`, voxels wholly more than `cut`
    std from the reading have likelihood 0 (mrfmap's departure, docs/ALGORITHMS.md 3)."""
    n = int(math.ceil(stop / r - 1e-12))
    a = np.arange(n) * r
    b = np.minimum(a + r, stop)
    nu = (upper((a - z) / sigma) - upper((b - z) / sigma)) / (b - a)
    if cut is not None:
        nu[((a - z) / sigma > cut) | ((b - z) / sigma < -cut)] = 0.0
    beyond = (upper((stop - z) / sigma) - upper((stop + r - z) / sigma)) / r
    return nu, beyond


def cause_model(means, nu, beyond):
    """The paper's sensor cause model q(j), j = 1..N and the final cause, normalised."""
    log_free = np.concatenate([[0.0], np.cumsum(np.log1p(-means))])
    prior = np.concatenate([means * np.exp(log_free[:-1]), [np.exp(log_free[-1])]])
    q = np.concatenate([nu, [beyond]]) * prior
    return q / q.sum()


class Column:
    """Voxel pdfs along the column. With `allocate`, mrfmap's departure (docs/ALGORITHMS.md
    5.2): a voxel whose first update moves its mean less than 0.001 from 1/2 stays unknown
    (its pdf uniform) and the update is dropped."""

    def __init__(self, particles, voxels, allocate=False):
        self.m = np.linspace(0.0, 1.0, particles)
        self.pdf = np.full((voxels, particles), 1.0 / particles)
        self.known = np.zeros(voxels, dtype=bool) if allocate else None

    def means(self, n=None):
        p = self.pdf[:n]
        return (p @ self.m) / p.sum(axis=1)

    def update(self, nu, beyond):
        n = len(nu)
        mean = np.clip(self.means(n), 1e-9, 1 - 1e-9)
        q = cause_model(mean, nu, beyond)
        on = q[:n]
        before = np.cumsum(on) - on
        after = q.sum() - before - on
        # p(z | m_i) with the other voxels at their means: the causes before i do not depend on
        # m_i, cause i scales with m_i / mean_i, the later ones with (1 - m_i) / (1 - mean_i).
        alpha = on / mean - after / (1 - mean)
        beta = before + after / (1 - mean)
        old = self.pdf[:n].copy()
        self.pdf[:n] *= alpha[:, None] * self.m[None, :] + beta[:, None]
        self.pdf[:n] /= self.pdf[:n].sum(axis=1, keepdims=True)
        if self.known is not None:
            new = ~self.known[:n] & (np.abs(self.means(n) - 0.5) < 0.001)
            self.pdf[:n][new] = old[new]
            self.known[:n] |= ~new


def png16(path, value):
    """A 1 x 1 16-bit greyscale PNG."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    raw = b"\x00" + struct.pack(">H", value)
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 1, 1, 16, 0, 0, 0, 0))
                + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def engine_column(a, readings, r, voxels, folder):
    """mrfmap's CRM means along the column for the same readings (unknown voxels as NaN)."""
    os.makedirs(f"{folder}/depth", exist_ok=True)
    scale = 5000.0
    with open(f"{folder}/camera.toml", "w") as f:
        f.write(f"fx = 1.0\nfy = 1.0\ncx = 0.0\ncy = 0.0\nwidth = 1\nheight = 1\ndepth_scale = {scale}\n")
    with open(f"{folder}/noise.toml", "w") as f:
        f.write(f"bias = [0.0, 0.0, 0.0]\nstd = [{a.sigma}, 0.0, 0.0]\n")
    # The camera inside a voxel's cross-section at every resolution, looking along +z.
    x, y = 0.00131, 0.00273
    with open(f"{folder}/depth.txt", "w") as d, open(f"{folder}/groundtruth.txt", "w") as g:
        for k, z in enumerate(readings):
            png16(f"{folder}/depth/{k:06d}.png", int(round(z * scale)))
            d.write(f"{k}.0 depth/{k:06d}.png\n")
            g.write(f"{k}.0 {x} {y} 0.0 0.0 0.0 0.0 1.0\n")
    m = f"{folder}/map.mrfmap"
    subprocess.run([a.mrfmap, "-q", "build", folder, "-o", m, "--engine", "crm", "--resolution", str(r),
                    "--particles", str(a.particles), "--noise", f"{folder}/noise.toml", "--threads", "1"],
                   check=True, capture_output=True, text=True)
    with open(f"{folder}/points.csv", "w") as f:
        for j in range(voxels):
            f.write(f"{x},{y},{(j + 0.5) * r}\n")
    out = subprocess.run([a.mrfmap, "query", m, "--points", f"{folder}/points.csv", "--json"],
                         check=True, capture_output=True, text=True).stdout
    return np.array([p["occupancy"] if p["known"] else np.nan for p in json.loads(out)["points"]])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mrfmap", help="an mrfmap binary, to compare its engine with this implementation")
    ap.add_argument("--sigma", type=float, default=0.13)
    ap.add_argument("--depth", type=float, default=3.6)
    ap.add_argument("--rays", type=int, default=100)
    ap.add_argument("--particles", type=int, default=101)
    ap.add_argument("--resolutions", default="0.05,0.02,0.01")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    readings = a.depth + a.sigma * rng.standard_normal(a.rays)
    print(f"wall at {a.depth} m, {a.rays} readings with std {a.sigma} m, uniform pdfs, {a.particles} particles\n")
    print("| voxel (m) | delta = 0.69 sigma^2 / r (m) | first reading's cause peak, in front of it (m) "
          f"| after {a.rays} readings: first voxel with mean > 0.2, in front of the wall (m) "
          "| largest mean within 2 std of the wall | mrfmap's engine against this (6-std cut in both): largest difference of means |")
    print("|---|---|---|---|---|---|")
    worst = 0.0
    for r in map(float, a.resolutions.split(",")):
        voxels = int(math.ceil((readings.max() + 3 * a.sigma) / r)) + 1
        col = Column(a.particles, voxels)
        first_peak = None
        for z in readings:
            nu, beyond = likelihoods(z, r, a.sigma, z + 3 * a.sigma)
            if first_peak is None:
                q = cause_model(col.means(len(nu)).clip(1e-9, 1 - 1e-9), nu, beyond)
                first_peak = z - (np.argmax(q[:-1]) + 0.5) * r
            col.update(nu, beyond)
        means = col.means()
        # Where the band of voxels the readings could not resolve starts. (Free voxels keep a
        # mean of 1 / (n + 2) after n readings here, one ray per voxel per reading: in a depth
        # image, voxels near the camera are crossed by many rays a frame. Hence 0.2, not the
        # voxel where a view's visibility drops most, which in one column is the first voxel
        # for a few dozen readings.)
        band = np.nonzero(means > 0.2)[0]
        seen = a.depth - band[0] * r if len(band) else float("nan")
        centres = (np.arange(voxels) + 0.5) * r
        near = means[np.abs(centres - a.depth) <= 2 * a.sigma].max()
        diff = "not run"
        if a.mrfmap:
            # mrfmap cuts the likelihood 6 std from the reading and leaves voxels unknown that
            # no single reading moves by 0.001: the same here for the comparison.
            cut = Column(a.particles, voxels, allocate=True)
            for z in readings:
                cut.update(*likelihoods(z, r, a.sigma, z + 3 * a.sigma, cut=6.0))
            with tempfile.TemporaryDirectory() as folder:
                theirs = engine_column(a, readings, r, voxels, folder)
            known = ~np.isnan(theirs)
            d = np.abs(np.where(known, theirs, 0.5) - cut.means())
            worst = max(worst, d.max())
            same = "the same" if np.array_equal(known, cut.known) else "not the same"
            diff = f"{d.max():.4f} ({known.sum()} of {voxels} known, {same} voxels as here)"
        print(f"| {r} | {math.log(2.0) * a.sigma ** 2 / r:.3f} | {first_peak:.3f} | {seen:.3f} | {near:.3f} | {diff} |")
    if a.mrfmap:
        print(f"\nlargest difference between the two implementations' means: {worst:.4f}")


if __name__ == "__main__":
    main()
