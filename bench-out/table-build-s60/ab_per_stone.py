import sys, time, json, numpy as np
from fem.scene import load
from planner import surrogate as su
prior = load(sys.argv[1]).prior()
g = su.Grid()
x0 = np.arange(0.0, prior.tissue.width_m + 1e-12, g.dx0_m)
shared = {"prior": prior.to_dict(), "levels_m": list(g.levels_m), "x0_m": x0}
stones = [(0.02, 0.012, 0.006), (0.035, 0.02, 0.01), (0.04, 0.009, 0.004), (0.03, 0.016, 0.012)]
su._one_stone(shared, stones[0])
ts, outs = [], []
for s in stones:
    t = time.perf_counter(); outs.append(su._one_stone(shared, s)); ts.append(time.perf_counter() - t)
np.save(sys.argv[2], np.array(outs))
print(json.dumps({"per_stone_s": ts, "median_s": float(np.median(ts))}))
