import json, sys
runs = sys.argv[1:]
data = {}
for r in runs:
    L = [json.loads(l) for l in open(f'{r}.log.jsonl') if '"validation"' not in l]
    data[r] = L
def window(L, t0, t1, key):
    v = [x[key] for x in L if t0 <= x['seconds'] < t1 and x['stage'] == 'joint' and x[key] > 0]
    return sum(v)/len(v) if v else float('nan'), len(v)
mx = min(max(x['seconds'] for x in L) for L in data.values())
edges = [i*mx/6 for i in range(7)]
print('window(s)', ' '.join(f'{r:>22}' for r in runs))
for a, b in zip(edges, edges[1:]):
    row = []
    for r in runs:
        p, n = window(data[r], a, b, 'psnr'); c, _ = window(data[r], a, b, 'camera'); 
        row.append(f'psnr {p:5.2f} cam {c:.3f} n{n:3d}')
    print(f'{a:5.0f}-{b:5.0f}', ' '.join(row))
for r in runs: print(r, 'steps', data[r][-1]['step'])
