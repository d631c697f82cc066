"""Per evaluate dir: mean +- se, first-close distance median, far closes, corners never lifted (picker 0..n)."""
import sys, glob, pandas as pd
for d in sys.argv[1:]:
    try:
        e = pd.read_csv(f"{d}/episodes.csv")
    except FileNotFoundError:
        print(d, "(not yet)"); continue
    e = e[e.state_noise == 0]
    cs = pd.concat([e[c] for c in e.columns if c.endswith("_first_close_cm")])
    lifted = pd.concat([e[c] for c in e.columns if c.endswith("_corner_lifted")]).astype(bool)
    f = e.final_normalized_performance
    print(f"{d.split('/')[-1]}: {f.mean():.3f} +- {f.std()/len(f)**.5:.3f} | first close median {cs.median():.2f} cm,"
          f" beyond 4.5 cm {int((cs > 4.5).sum())} of {int(cs.notna().sum())}, never lifted {int((~lifted).sum())}")
