import json, sys
cols = sys.argv[2].split(",")
print("| " + " | ".join(cols) + " |"); print("|" + "---|" * len(cols))
for l in open(sys.argv[1]):
    d = json.loads(l)
    print("| " + " | ".join((f"{d[c]:+.1%}" if ("vs" in c or "over_exact" in c) else f"{d[c]:.3g}") if isinstance(d[c], float) else str(d[c]) for c in cols) + " |")
