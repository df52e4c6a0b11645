from tests.envmap.test_cube import *
for f in ("anisotropic", "ewa"):
  for k in (0, 1):
    cube, d = grad_inputs()
    dx = torch.full_like(d, 0.1).detach()
    if k == 0: dx[0, 0, 0, 0] = float("nan")
    else: dx[0, 0, 0, 1] = float("inf")
    dx.requires_grad_()
    dy = torch.zeros_like(dx, requires_grad=True)
    out = cubemap(cube, d, filter=f, dirs_dx=dx, dirs_dy=dy)
    grads = torch.autograd.grad(out.sum(), (cube, d, dx, dy))
    print(f, k, out.isfinite().all().item(), [(~g.isfinite()).any(-1)[0,0].nonzero().flatten().tolist() for g in grads[1:]])
