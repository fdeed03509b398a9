import json, sys
for path in sys.argv[1:]:
    lines = [json.loads(l) for l in open(path)]
    ws = [l for l in lines if l["kind"] == "worker"]
    fr = sorted({w["frame"] for w in ws})
    out = []
    for f in fr:
        n = [w["samples"] for w in ws if w["frame"] == f]
        r = [w["render_s"] for w in ws if w["frame"] == f]
        out.append(f"{max(n)/(sum(n)/len(n)):.2f}/{max(r)/(sum(r)/len(r)):.2f}")
    print(path.split('/')[-2], " ".join(out))
