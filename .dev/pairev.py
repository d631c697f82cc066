"""Paired per-episode B - A of two evaluate.py run dirs (same configurations), at each state_noise level."""
import sys, pandas as pd, numpy as np
a, b = (pd.read_csv(f"{d}/episodes.csv") for d in sys.argv[1:3])
col = [c for c in a.columns if "normalized" in c or c == "performance"][0]
for lvl in sorted(set(a.get("state_noise", pd.Series([0])))):
    x = a[a.state_noise == lvl] if "state_noise" in a else a
    y = b[b.state_noise == lvl] if "state_noise" in b else b
    m = x.merge(y, on="episode", suffixes=("_a", "_b"))
    d = m[col + "_b"] - m[col + "_a"]
    print(f"noise {lvl}: n={len(d)} A {m[col+'_a'].mean():.3f} B {m[col+'_b'].mean():.3f} B-A {d.mean():+.3f} +- {d.std(ddof=1)/np.sqrt(len(d)):.3f}")
