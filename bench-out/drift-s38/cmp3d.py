import json, sys, glob, os
for s in range(6):
    for v in ("old", "new"):
        f = f"/tmp/ab3d/{v}-{s}/result.json"
        if not os.path.exists(f):
            continue
        d = json.load(open(f)); e = d["estimate"]; er = d["sim"]["error"]; n = d.get("nuisance", {})
        z = {k: er[k] / e[k]["sigma"] for k in ("x_m", "y_m", "depth_m", "diameter_m")}
        dr = n.get("sensor_drift_n_per_s", {}); off = n.get("surface_offset_m", {})
        print(f"seed {s} {v}: det {d['detected']} z x {z['x_m']:+.2f} y {z['y_m']:+.2f} depth {z['depth_m']:+.2f} diam {z['diameter_m']:+.2f}"
              f" | depth err {er['depth_m']*1e3:+.2f} mm diam err {er['diameter_m']*1e3:+.2f} mm | drift {dr.get('value',0)*1e3:+.3f}+-{dr.get('sigma',0)*1e3:.3f} mN/s offset {off.get('value',0)*1e3:+.3f} mm")
