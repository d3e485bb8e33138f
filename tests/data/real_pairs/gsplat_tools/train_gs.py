#!/usr/bin/env python3
"""Full-resolution 3DGS training with gsplat (the Inria recipe via gsplat's DefaultStrategy).
usage: train_gs.py SCENE_DIR OUT_PREFIX MAX_STEPS DEADLINE_UNIX [SAVE_AT,...]
SCENE_DIR holds transforms.json (nerfstudio, OpenGL c2w), images/, points3d.ply (ascii xyz rgb).
Writes OUT_PREFIX_<step>.ply (Inria property names, SH0 only: f_rest dropped for size) and OUT_PREFIX.log."""
import json, math, os, sys, time
import numpy as np
import torch
import torch.nn.functional as Fn
from PIL import Image
from gsplat import rasterization
from gsplat.strategy import DefaultStrategy

scene, prefix, max_steps, deadline = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
save_at = sorted(int(s) for s in sys.argv[5].split(',')) if len(sys.argv) > 5 else []
dev = 'cuda'
torch.manual_seed(0)
logf = open(prefix + '.log', 'w')
def log(*a):
    s = ' '.join(str(x) for x in a); print(s, flush=True); logf.write(s + '\n'); logf.flush()

tj = json.load(open(os.path.join(scene, 'transforms.json')))
imgs, views, Ks, centres = [], [], [], []
for f in tj['frames']:
    im = np.asarray(Image.open(os.path.join(scene, f['file_path'])).convert('RGB'), dtype=np.float32) / 255.0
    imgs.append(torch.from_numpy(im))
    M = np.array(f['transform_matrix'], dtype=np.float64)
    Rc2w = M[:3, :3] @ np.diag([1.0, -1.0, -1.0]); C = M[:3, 3]
    R = Rc2w.T; t = -R @ C
    V = np.eye(4); V[:3, :3] = R; V[:3, 3] = t
    views.append(V); centres.append(C)
    Ks.append([[f['fl_x'], 0, f['cx']], [0, f['fl_y'], f['cy']], [0, 0, 1]])
H, W = imgs[0].shape[:2]
imgs = torch.stack(imgs).to(dev)
viewmats = torch.tensor(np.array(views), dtype=torch.float32, device=dev)
Ks = torch.tensor(np.array(Ks), dtype=torch.float32, device=dev)
centres = np.array(centres)
scene_scale = float(np.linalg.norm(centres - centres.mean(0), axis=1).max()) * 1.1
log(f'views {len(imgs)} {W}x{H} scene_scale {scene_scale:.4f}')

# init from the sparse points (ascii PLY: x y z r g b)
lines = open(os.path.join(scene, 'points3d.ply')).read().split('\n')
h = lines.index('end_header')
P = np.array([[float(x) for x in l.split()] for l in lines[h + 1:] if l.strip()])
pts = torch.tensor(P[:, :3], dtype=torch.float32, device=dev)
rgb = torch.tensor(P[:, 3:6] / 255.0, dtype=torch.float32, device=dev)
N = len(pts)
d = torch.cdist(pts, pts); d.fill_diagonal_(float('inf'))
dist2 = (d.topk(3, largest=False).values ** 2).mean(-1)
SH_C0 = 0.28209479177387814
params = torch.nn.ParameterDict({
    'means': torch.nn.Parameter(pts.clone()),
    'scales': torch.nn.Parameter(torch.log(torch.sqrt(dist2)).unsqueeze(-1).repeat(1, 3)),
    'quats': torch.nn.Parameter(torch.rand(N, 4, device=dev)),
    'opacities': torch.nn.Parameter(torch.logit(torch.full((N,), 0.1, device=dev))),
    'sh0': torch.nn.Parameter(((rgb - 0.5) / SH_C0).unsqueeze(1)),
    'shN': torch.nn.Parameter(torch.zeros(N, 15, 3, device=dev)),
})
lrs = {'means': 1.6e-4 * scene_scale, 'scales': 5e-3, 'quats': 1e-3, 'opacities': 5e-2, 'sh0': 2.5e-3, 'shN': 2.5e-3 / 20}
opts = {k: torch.optim.Adam([{'params': params[k], 'lr': lrs[k], 'name': k}], eps=1e-15) for k in params}
means_sched = torch.optim.lr_scheduler.ExponentialLR(opts['means'], gamma=0.01 ** (1.0 / max_steps))
strategy = DefaultStrategy(verbose=False)
strategy.check_sanity(params, opts)
state = strategy.initialize_state(scene_scale=scene_scale)
bg = torch.ones(1, 3, device=dev)

def gauss_window(size=11, sigma=1.5):
    g = torch.exp(-(torch.arange(size, device=dev) - size // 2) ** 2 / (2 * sigma ** 2)); g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(3, 1, size, size).contiguous()
WIN = gauss_window()
def ssim(a, b):  # a, b: [1, 3, H, W]
    mu_a = Fn.conv2d(a, WIN, padding=5, groups=3); mu_b = Fn.conv2d(b, WIN, padding=5, groups=3)
    saa = Fn.conv2d(a * a, WIN, padding=5, groups=3) - mu_a ** 2
    sbb = Fn.conv2d(b * b, WIN, padding=5, groups=3) - mu_b ** 2
    sab = Fn.conv2d(a * b, WIN, padding=5, groups=3) - mu_a * mu_b
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return (((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (saa + sbb + c2))).mean()

def render(idx, sh_degree):
    colors = torch.cat([params['sh0'], params['shN']], 1)
    return rasterization(params['means'], params['quats'], torch.exp(params['scales']), torch.sigmoid(params['opacities']),
                         colors, viewmats[idx], Ks[idx], W, H, sh_degree=sh_degree, packed=False, backgrounds=bg.expand(len(idx), 3))

def save(step):
    with torch.no_grad():
        n = len(params['means'])
        q = params['quats'] / params['quats'].norm(dim=-1, keepdim=True)
        cols = [params['means'], torch.zeros(n, 3, device=dev), params['sh0'].reshape(n, 3),
                params['opacities'].reshape(n, 1), params['scales'], q]
        a = torch.cat(cols, 1).float().cpu().numpy().astype('<f4')
    props = ['x', 'y', 'z', 'nx', 'ny', 'nz'] + [f'f_dc_{i}' for i in range(3)] + \
            ['opacity', 'scale_0', 'scale_1', 'scale_2', 'rot_0', 'rot_1', 'rot_2', 'rot_3']
    assert a.shape[1] == len(props)
    hdr = 'ply\nformat binary_little_endian 1.0\n' + f'comment gsplat 1.5.3 DefaultStrategy, {W}x{H}, step {step}; trained with SH degree 3, saved SH0 only (f_rest dropped for size)\n' + \
          f'element vertex {n}\n' + ''.join(f'property float {p}\n' for p in props) + 'end_header\n'
    with open(f'{prefix}_{step}.ply', 'wb') as fh:
        fh.write(hdr.encode()); fh.write(a.tobytes())
    log(f'saved {prefix}_{step}.ply: {n} Gaussians')

t0 = time.time(); step = 0
order = torch.randperm(len(imgs))
for step in range(max_steps):
    if time.time() > deadline:
        log(f'deadline reached at step {step}'); break
    i = int(order[step % len(order)])
    if step % len(order) == len(order) - 1:
        order = torch.randperm(len(imgs))
    idx = torch.tensor([i], device=dev)
    out, alphas, info = render(idx, min(step // 1000, 3))
    strategy.step_pre_backward(params, opts, state, step, info)
    gt = imgs[i:i + 1]
    l1 = (out - gt).abs().mean()
    ss = ssim(out.permute(0, 3, 1, 2), gt.permute(0, 3, 1, 2))
    loss = 0.8 * l1 + 0.2 * (1 - ss)
    loss.backward()
    strategy.step_post_backward(params, opts, state, step, info, packed=False)
    for o in opts.values():
        o.step(); o.zero_grad(set_to_none=True)
    means_sched.step()
    if step % 1000 == 0:
        log(f'step {step} loss {loss.item():.4f} l1 {l1.item():.4f} n {len(params["means"])} t {time.time() - t0:.1f}s')
    if step + 1 in save_at:
        save(step + 1)
steps_done = step + 1 if time.time() <= deadline else step
with torch.no_grad():
    ps = []
    for i in range(len(imgs)):
        out, _, _ = render(torch.tensor([i], device=dev), 3)
        mse = ((out.clamp(0, 1) - imgs[i:i + 1]) ** 2).mean().item()
        ps.append(-10 * math.log10(max(mse, 1e-12)))
log(f'train-view PSNR mean {np.mean(ps):.2f} min {np.min(ps):.2f} after {steps_done} steps, {time.time() - t0:.1f}s')
if steps_done not in save_at:
    save(steps_done)
