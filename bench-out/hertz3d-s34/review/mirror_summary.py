import json, collections
rows = [json.loads(l) for f in ("out3d_mirror.jsonl", "out3d_nu045.jsonl") for l in open(f"/tmp/review34/{f}")]
rows = [r for r in rows if r["patch_over_r"] == 2.6]
g = collections.defaultdict(dict)
for r in rows:
    g[(r["nu"], r["fine_over_r"], r["grade"], r["d_over_r"])][(r["x_off_over_r"], r["y_off_over_r"])] = r
print("| nu | fine/R | grade | d/R | vM vs Hertz: centre / A(-.27,+.11) / A mirrored x->W-x / A mirrored y->W-y | vM A vs x-mirror | vM A vs y-mirror | force A vs x-mirror | force A vs y-mirror | depth/a A, x-mirror |")
print("|---|---|---|---|---|---|---|---|---|---|")
for k, d in g.items():
    c, A, Ax, Ay = d[(0.0, 0.0)], d[(-0.27, 0.11)], d[(0.27, 0.11)], d[(-0.27, -0.11)]
    f = lambda p, q, key: p[key] / q[key] - 1
    print(f"| {k[0]} | {k[1]} | {k[2]} | {k[3]} | {c['vm_vs_hertz']:+.1%} / {A['vm_vs_hertz']:+.1%} / {Ax['vm_vs_hertz']:+.1%} / {Ay['vm_vs_hertz']:+.1%} | "
          f"{f(A, Ax, 'max_vm_pa'):+.1%} | {f(A, Ay, 'max_vm_pa'):+.1%} | {((1+A['force_vs_hertz'])/(1+Ax['force_vs_hertz'])-1):+.2%} | {((1+A['force_vs_hertz'])/(1+Ay['force_vs_hertz'])-1):+.2%} | {A['vm_depth_over_a']:.2f}, {Ax['vm_depth_over_a']:.2f} |")
