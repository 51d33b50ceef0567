#!/usr/bin/env python3
"""Belief propagation on the smallest scene where voxels compete: two voxels, A in front of B,
on every ray of K keyframes with n identical rays each, scheduled as the MRF engine does
(a keyframe's rays against the same sums, keyframes in turn, a message whose change reverses
halved, undamped after three calm traces), against the exact posterior.

Ray factor: `a` if A is occupied, `b` if A is free and B occupied, `e` if both are free; prior
0.1. With `a / b` near 1 (a likelihood several voxels wide) the run can stop on "A occupied"
when the exact answer is B: the marginals sit at 0 or 1 and barely move while damped messages
are still far from their values. Counting what damping held back (as `run_until` does since
session 15) fixes it. docs/history/RESULTS.md ("Why the MRF converges slowly at 0.02 m") says
what it found.

Usage: python3 bench/column_bp.py
"""
import math


def logit(x):
    return math.log(x / (1 - x))


def sig(s):
    return 1 / (1 + math.exp(-max(-700.0, min(700.0, s))))


def exact(a, b, e, p, rays):
    """Exact marginals of A and B given `rays` identical rays."""
    la = math.log(p) + rays * math.log(a)
    lb = math.log((1 - p) * p) + rays * math.log(b)
    le = 2 * math.log(1 - p) + rays * math.log(e)
    top = max(la, lb, le)
    wa, wb, we = (math.exp(x - top) for x in (la, lb, le))
    z = wa + wb + we
    return wa / z, (wb + wa * p) / z


def bp(a, b, e, p, keyframes, n, held_back, tol=1e-3, max_sweeps=3000):
    """Sweeps until no marginal moves by more than `tol` (and, with `held_back`, no damped
    update left more than `tol` undone); returns (sweeps or None, marginal A, marginal B)."""
    msg = [[0.0, 0.0] for _ in range(keyframes)]
    level = [[0, 0] for _ in range(keyframes)]
    calm = [[0, 0] for _ in range(keyframes)]
    sign = [[0.0, 0.0] for _ in range(keyframes)]
    s = [logit(p), logit(p)]
    for sweep in range(max_sweeps):
        moved = 0.0
        for k in range(keyframes):
            # Cavities: everything but one ray's share of this keyframe's message.
            qa, qb = sig(s[0] - msg[k][0] / n), sig(s[1] - msg[k][1] / n)
            new = [
                n * math.log(a / (qb * b + (1 - qb) * e)),
                n * math.log((qa * a + (1 - qa) * b) / (qa * a + (1 - qa) * e)),
            ]
            before = [sig(s[0]), sig(s[1])]
            for j in range(2):
                change = new[j] - msg[k][j]
                if sweep > 0:
                    if change * sign[k][j] < 0:
                        level[k][j], calm[k][j] = min(level[k][j] + 1, 8), 0
                    elif calm[k][j] + 1 >= 3:
                        level[k][j], calm[k][j] = max(level[k][j] - 1, 0), 0
                    else:
                        calm[k][j] += 1
                step = change / 2 ** level[k][j]
                sign[k][j] = math.copysign(1.0, step) if step else 0.0
                s[j] += step
                msg[k][j] += step
                if held_back:
                    moved = max(moved, abs(sig(s[j] + change - step) - sig(s[j])))
            moved = max(moved, abs(sig(s[0]) - before[0]), abs(sig(s[1]) - before[1]))
        if moved < tol:
            return sweep + 1, sig(s[0]), sig(s[1])
    return None, sig(s[0]), sig(s[1])


def main():
    print("a/b   K    n | marginals only: sweeps  A      B     | + held back: sweeps  A      B     | exact A  B")
    for ratio in (0.8, 0.9, 0.95, 0.98):
        for keyframes, n in ((10, 10), (10, 100), (30, 30), (5, 200)):
            plain = bp(ratio, 1.0, 1e-4, 0.1, keyframes, n, False)
            held = bp(ratio, 1.0, 1e-4, 0.1, keyframes, n, True)
            ea, eb = exact(ratio, 1.0, 1e-4, 0.1, keyframes * n)
            print(
                f"{ratio:<5} {keyframes:<4} {n:<4} |        {str(plain[0]):>5}   {plain[1]:.3f}  {plain[2]:.3f} |"
                f"      {str(held[0]):>5}   {held[1]:.3f}  {held[2]:.3f} | {ea:.3f}  {eb:.3f}"
            )


if __name__ == "__main__":
    main()
