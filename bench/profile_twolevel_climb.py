"""Two-level closest hits: the depth-sized stack (stack_capacity) against the fixed STACK
with parent-link climbs (issue 43): rays per CPU second, warm, 20,000 random rays, hits
compared. python bench/profile_twolevel_climb.py (needs ../shared/data)."""
import time, resource, numpy as np, jax, jaxbvh
from pathlib import Path
from jaxbvh import scenes, twolevel, rays
from jaxbvh.io import load_mesh
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
cow = load_mesh(DATA / "meshes" / "cow.obj").objects[0]
sc = [("pile (12 cows)", scenes.pile(jax.random.key(5), *cow, 12)),
      ("drone", load_mesh(DATA / "scenes" / "drone" / "scene.gltf")),
      ("forest (64 trees)", scenes.instanced_scene(jax.random.key(0), [scenes.tree_mesh(jax.random.key(k)) for k in range(2)], 64, spread=0.5, upright=True, name="forest"))]
cpu = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_utime
for name, mesh in sc:
    tl = twolevel.build(mesh)
    lo, hi = mesh.local_boxes()
    single = jaxbvh.to_numpy(jaxbvh.build(lo, hi))
    o, d = rays.make_rays(jax.random.key(2), "random", single, None, 20000)
    out = {}
    for label, cap in (("depth-sized", twolevel.stack_capacity(tl)), ("STACK", None)):
        h = twolevel.closest_hit(tl, o, d, capacity=cap)  # compile
        c = cpu(); h = twolevel.closest_hit(tl, o, d, capacity=cap); c = cpu() - c
        out[label] = (cap, 20000 / c, h)
    a, b = out["depth-sized"], out["STACK"]
    print(f"{name:20s} depth-sized stack {a[0]} : {a[1]:,.0f} rays/CPU-s | STACK 64: {b[1]:,.0f} | same prims {np.array_equal(a[2].prim, b[2].prim)} box {a[2].box_tests.mean():.1f}/{b[2].box_tests.mean():.1f}", flush=True)
