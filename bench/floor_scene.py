#!/usr/bin/env python3
"""Writes the scene file of a multi-room floor (issue #36's scene): a grid of ROOMS x ROOMS
rooms of ROOM metres, walls with a doorway between every two neighbouring rooms, a few pieces
of furniture per room, and a path through every room (serpentine, through the doorways) seen
by a low-resolution depth camera with D435-like noise. Deterministic: the same arguments give
the same file.

usage: bench/floor_scene.py OUT.toml [--rooms 4] [--room 10] [--frames 2000]
       (the committed results/scenes/floor.toml: the defaults, a 40 m x 40 m floor)
"""
import argparse

p = argparse.ArgumentParser()
p.add_argument("out")
p.add_argument("--rooms", type=int, default=4)
p.add_argument("--room", type=float, default=10.0)
p.add_argument("--frames", type=int, default=2000)
p.add_argument("--width", type=int, default=160)
p.add_argument("--height", type=int, default=120)
a = p.parse_args()

n, room, t, h, door = a.rooms, a.room, 0.2, 2.5, 1.2
size = n * room
lines = [
    f"# A {size:g} m x {size:g} m floor of {n} x {n} rooms, written by bench/floor_scene.py "
    f"--rooms {n} --room {room:g} --frames {a.frames}",
    "",
    "[camera]",
    f"fx = {0.75 * a.width:.1f}",
    f"fy = {0.75 * a.width:.1f}",
    f"cx = {a.width / 2 - 0.5}",
    f"cy = {a.height / 2 - 0.5}",
    f"width = {a.width}",
    f"height = {a.height}",
    "depth_scale = 5000.0",
    "min_depth = 0.3",
    "max_depth = 6.0",
    "",
    "[noise]",
    "bias = [0.0, 0.0, 0.004]",
    "std = [0.002, 0.0, 0.0035]",
    "",
]


def box(lo, hi):
    lines.extend(["[[box]]", f"min = [{lo[0]:g}, {lo[1]:g}, {lo[2]:g}]", f"max = [{hi[0]:g}, {hi[1]:g}, {hi[2]:g}]"])


def cylinder(x, y, r, z1):
    lines.extend(["[[cylinder]]", f"center = [{x:g}, {y:g}]", f"radius = {r:g}", f"z = [0.0, {z1:g}]"])


box((0, 0, -0.1), (size, size, 0))
# Outer walls.
box((-t, -t, 0), (size + t, 0, h))
box((-t, size, 0), (size + t, size + t, h))
box((-t, 0, 0), (0, size, h))
box((size, 0, 0), (size + t, size, h))
# Inner walls along x = k room and y = k room, a doorway in the middle of each room's stretch.
for k in range(1, n):
    c = k * room
    for j in range(n):
        lo, hi = j * room, (j + 1) * room
        mid = (lo + hi) / 2
        box((c - t / 2, lo, 0), (c + t / 2, mid - door / 2, h))
        box((c - t / 2, mid + door / 2, 0), (c + t / 2, hi, h))
        box((lo, c - t / 2, 0), (mid - door / 2, c + t / 2, h))
        box((mid + door / 2, c - t / 2, 0), (hi, c + t / 2, h))
# Furniture: a table, a cabinet against a wall and a column per room, placed by a fixed rule.
for i in range(n):
    for j in range(n):
        x0, y0 = i * room, j * room
        s = (i * 7 + j * 3) % 5
        box((x0 + 2 + 0.3 * s, y0 + 6, 0), (x0 + 3.5 + 0.3 * s, y0 + 7, 0.75))
        box((x0 + 0.1 + t / 2, y0 + 1 + 0.5 * s, 0), (x0 + 0.6 + t / 2, y0 + 2.5 + 0.5 * s, 1.8))
        cylinder(x0 + 7 - 0.4 * s, y0 + 3, 0.25, 2.5)
lines.append("")
# The path: serpentine over the rows of rooms, through each room's middle and the doorways.
z = 1.2
way = []
for j in range(n):
    cols = range(n) if j % 2 == 0 else reversed(range(n))
    cols = list(cols)
    for idx, i in enumerate(cols):
        cx, cy = (i + 0.5) * room, (j + 0.5) * room
        way.append((cx, cy - 1.5, z))
        way.append((cx, cy + 1.5, z))
        if idx + 1 < len(cols):
            nxt = cols[idx + 1]
            wall = max(i, nxt) * room
            way.append((wall - 1.0 if nxt > i else wall + 1.0, cy, z))
            way.append((wall + 1.0 if nxt > i else wall - 1.0, cy, z))
    if j + 1 < n:
        i = cols[-1]
        cx, wall = (i + 0.5) * room, (j + 1) * room
        way.append((cx, wall - 1.0, z))
        way.append((cx, wall + 1.0, z))
lines.append("[path]")
lines.append("waypoints = [" + ", ".join(f"[{x:g}, {y:g}, {zz:g}]" for x, y, zz in way) + "]")
lines.append(f"frames = {a.frames}")
lines.append("sweep_deg = 90.0")
lines.append("sweep_period = 40.0")
open(a.out, "w").write("\n".join(lines) + "\n")
