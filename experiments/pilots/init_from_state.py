# Usage: init_from_state.py [--one-token-set] STATE.safetensors OUT.safetensors [N W]
# The geometry tensors of a flexsplat state or model file as a VGGT-layout file for `flexsplat train --init` (pilots
# that start from a run's geometry); with N W the depth head gains N image convolutions of width W
# (depth_image_convs; Kaiming-uniform weights, zero bias) and zero output_conv2.0 weights on their channels, so that
# the depth starts as the state's. --one-token-set keeps only the camera and register tokens of the frames after the
# first (set 1 of VGGT's 2) for a model with frame_tokens 1.
import json, struct, sys, array, random, math
one_set = '--one-token-set' in sys.argv
if one_set: sys.argv.remove('--one-token-set')
if len(sys.argv) not in (3, 5):
    sys.exit('usage: init_from_state.py [--one-token-set] STATE.safetensors OUT.safetensors [N W]')
src, dst = sys.argv[1], sys.argv[2]
convs = int(sys.argv[3]) if len(sys.argv) > 3 else 0
width = int(sys.argv[4]) if len(sys.argv) > 4 else 16
f = open(src, 'rb'); n = struct.unpack('<Q', f.read(8))[0]; h = json.loads(f.read(n)); base = 8 + n
out = {}
for k, v in h.items():
    if k == '__metadata__' or k.split('.')[0] not in ('aggregator', 'camera_head', 'depth_head', 'match_head'): continue
    if v['dtype'] != 'F32': sys.exit(f"{src}: tensor {k} is {v['dtype']}, expected F32")
    f.seek(base + v['data_offsets'][0]); a = array.array('f'); a.frombytes(f.read(v['data_offsets'][1] - v['data_offsets'][0]))
    out[k] = (v['shape'], a)
rng = random.Random(5)
if one_set:
    for k in ('aggregator.camera_token', 'aggregator.register_token'):
        shape, a = out[k]
        if shape[1] != 2: sys.exit(f"{src}: {k} has {shape[1]} token sets, expected 2")
        per = len(a) // 2
        out[k] = ([shape[0], 1] + shape[2:], a[per:])
if convs:
    k = 'depth_head.scratch.output_conv2.0.weight'; shape, a = out[k]; co, ci, kh, kw = shape
    b = array.array('f', [0.0] * (co * (ci + width) * kh * kw))
    for o in range(co):
        for i in range(ci):
            for t in range(kh * kw): b[(o * (ci + width) + i) * kh * kw + t] = a[(o * ci + i) * kh * kw + t]
    out[k] = ([co, ci + width, kh, kw], b)
    for j in range(convs):
        cin = 3 if j == 0 else width; bound = math.sqrt(6.0 / (cin * 9))
        out['depth_head.scratch.image_conv.%d.weight' % j] = ([width, cin, 3, 3], array.array('f', [rng.uniform(-bound, bound) for _ in range(width * cin * 9)]))
        out['depth_head.scratch.image_conv.%d.bias' % j] = ([width], array.array('f', [0.0] * width))
hdr = {}; off = 0
for k, (shape, a) in out.items():
    hdr[k] = {'dtype': 'F32', 'shape': shape, 'data_offsets': [off, off + 4 * len(a)]}; off += 4 * len(a)
hb = json.dumps(hdr).encode(); hb += b' ' * ((8 - len(hb) % 8) % 8)
with open(dst, 'wb') as g:
    g.write(struct.pack('<Q', len(hb))); g.write(hb)
    for k, (shape, a) in out.items(): g.write(a.tobytes())
print(dst, len(out), 'tensors')
