"""gamma = sum sigma_i^-2 of S_s U for the edge target and the Bernoulli target, beside the thesis's table.

Delbracio PhD thesis 2013, Table 2.2 (= IJCV 2012, Table 2): s = 4, ~80 x 80
window, supports 9 to 33. Our views: the whole Bernoulli target at one cell
per s-grid sample (80 x 80 pixels), and one tile of the edge target over
80 x 80 pixels turned by 10 degrees (psfd.estimator.gamma). The bound is
Lemma 3 of IJCV 2012 for the 64 x 64-pixel noise area (the thesis's
"effective window"). Also prints the time of one gamma, relative to the
time of the 9 x 9 Bernoulli gamma measured in the same run.

Run: python bench/bench_gamma.py
"""

from __future__ import annotations

import time

from psfd.estimator import gamma

S = 4
PIXELS = 80


def main() -> None:
    table = gamma.THESIS_TABLE
    views = {"edges": gamma.edge_view(S, PIXELS), "bernoulli": gamma.bernoulli_view(S)}
    print(f"gamma of S_s U, s = {S}, window {PIXELS}x{PIXELS} pixels (thesis Table 2.2 in brackets)")
    columns = ("edges", 22), ("bernoulli", 18), ("bound", 16), ("edges/bern", 18), ("bern/bound", 16), ("time", 6)
    print(f"{'support':>8} " + " ".join(f"{name:>{width}}" for name, width in columns))
    reference = None
    for i, r in enumerate(table["supports"]):
        values, seconds = {}, 0.0
        for kind, view in views.items():
            start = time.perf_counter()
            values[kind] = gamma.gamma(gamma.view_matrix(gamma.window_view(view, PIXELS, S, r), S, r))
            seconds += time.perf_counter() - start
        reference = reference or seconds
        noise_pixels = 256 // S
        b = gamma.bound(noise_pixels**2, r * r)
        e, n = values["edges"], values["bernoulli"]
        te, tn, tb = table["edges"][i], table["bernoulli"][i], table["bound"][i]
        print(f"{r:>5}x{r:<2} {e:>10.2f} [{te:>9.2f}] {n:>7.3f} [{tn:>5.2f}] {b:>6.3f} [{tb:>5.2f}] "
              f"{e / n:>8.0f} [{te / tn:>6.0f}] {n / b:>5.2f} [{tn / tb:>5.2f}] {seconds / reference:>5.1f}x")
    print("ratios: ours [thesis]; time relative to the 9x9 row of this run")


if __name__ == "__main__":
    main()
