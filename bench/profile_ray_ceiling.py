"""Ceiling experiment (issue 43): the leanest closest-hit walk XLA can run, beside the library's.

    BAR=1 python bench/profile_ray_ceiling.py        # with values computed once (see below)
    BAR=0 python bench/profile_ray_ceiling.py        # left to XLA's fusion

A binary-tree closest-hit walk with nothing but what a hit needs (no counters, no
climbs, no any/all modes, a stack as deep as the tree, the library's packed rows and
wavefront refill), written straight on [lanes] arrays. Its rays per CPU-second bound what
a rewrite of the step could gain under XLA's CPU compiler (bench/results/ray_anatomy.md).
``BAR=1`` passes the shared values (slab results, the read indices) through a reduce,
which XLA never fuses into its users, so they are not recomputed in every consumer.
Not a library path: the hits are checked against the library's, nothing more.
"""
import sys, resource, time
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
import jax, jax.numpy as jnp, numpy as np
import jaxbvh
from jaxbvh import rays
from jaxbvh.tree.layout import to_jax
from jaxbvh.rays.traversal import pack, inverse_direction, moller_trumbore_edges
from bench_rays import DATA, load_triangles, chain_tree
I32 = jnp.int32
BAR = int(__import__("os").environ.get("BAR", "1"))
def mat(x):
    """Computed once, apart (a reduce is never fused into its users)."""
    if not BAR:
        return x
    if x.dtype == jnp.bool_:
        return jnp.any(jnp.stack([x, jnp.zeros_like(x)]), axis=0)
    low = -jnp.inf if jnp.issubdtype(x.dtype, jnp.floating) else jnp.iinfo(x.dtype).min
    return jnp.max(jnp.stack([x, jnp.full_like(x, low)]), axis=0)

def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF); return r.ru_utime + r.ru_stime

from functools import partial
@partial(jax.jit, static_argnames=("S", "L", "W", "ITERS"))
def lean(node_tab, slot_tab, root, origin, direction, S=64, L=512, W=4, ITERS=4):
    R = origin.shape[0]
    inv = inverse_direction(direction)
    def ray_of(i):
        return origin[i], direction[i], inv[i]
    stack = jnp.zeros((L, S), I32)
    sentry = jnp.zeros((L, S), jnp.float32)
    lanes = jnp.arange(L)
    # state
    st = dict(ray=jnp.full(L, -1, I32), node=jnp.full(L, -1, I32), entry=jnp.zeros(L), sp=jnp.zeros(L, I32),
              t=jnp.full(L, jnp.inf), prim=jnp.full(L, -1, I32), lp=jnp.zeros(L, I32), le=jnp.zeros(L, I32))
    out_t = jnp.full(R + 1, jnp.inf); out_p = jnp.full(R + 1, -1, I32)
    def refill(c):
        st, stack, sentry, out_t, out_p, nxt = c
        done = (st["node"] < 0) & (st["sp"] <= 0) & (st["lp"] >= st["le"])
        has = st["ray"] >= 0
        w = jnp.where(done & has, st["ray"], R)
        out_t = out_t.at[w].set(st["t"]); out_p = out_p.at[w].set(st["prim"])
        new = nxt + jnp.cumsum(done.astype(I32)) - 1
        take = done & (new < R)
        st = dict(st)
        st["ray"] = jnp.where(take, new, jnp.where(done, -1, st["ray"]))
        st["node"] = jnp.where(take, root, st["node"]); st["entry"] = jnp.where(take, 0.0, st["entry"])
        st["sp"] = jnp.where(take, 0, st["sp"]); st["t"] = jnp.where(take, jnp.inf, st["t"])
        st["prim"] = jnp.where(take, -1, st["prim"])
        return st, stack, sentry, out_t, out_p, nxt + jnp.sum(take, dtype=I32)
    def step(_, c):
        st, stack, sentry = c
        st = dict(st)
        o = origin[jnp.maximum(st["ray"], 0)]; d = direction[jnp.maximum(st["ray"], 0)]; iv = inv[jnp.maximum(st["ray"], 0)]
        # node phase
        go = (st["node"] >= 0) & (st["lp"] >= st["le"])
        visit = go & (st["entry"] <= st["t"])
        row = node_tab[mat(jnp.where(visit, st["node"], 0))]
        lo0, hi0, lo1, hi1 = row[:, 0:3], row[:, 3:6], row[:, 6:9], row[:, 9:12]
        meta = jax.lax.bitcast_convert_type(row[:, 12:18], I32)
        def slab(lo, hi):
            t0 = (lo - o) * iv; t1 = (hi - o) * iv
            a = jnp.minimum(t0, t1); b = jnp.maximum(t0, t1)
            near = jnp.maximum(jnp.maximum(jnp.maximum(a[:, 0], a[:, 1]), a[:, 2]), 0.0)
            far = jnp.minimum(jnp.minimum(b[:, 0], b[:, 1]), b[:, 2])
            return near <= jnp.minimum(far, st["t"]), near
        h0, e0 = slab(lo0, hi0); h1, e1 = slab(lo1, hi1)
        h0, e0, h1, e1 = mat(h0), mat(e0), mat(h1), mat(e1)
        leaf = meta[:, 3] > 0
        h0 = h0 & ~leaf & (meta[:, 0] >= 0); h1 = h1 & ~leaf & (meta[:, 1] >= 0)
        first1 = e1 < e0
        near = jnp.where(first1, meta[:, 1], meta[:, 0]); far = jnp.where(first1, meta[:, 0], meta[:, 1])
        hn = jnp.where(first1, h1, h0); hf = jnp.where(first1, h0, h1)
        en = jnp.where(first1, e1, e0); ef = jnp.where(first1, e0, e1)
        both = visit & hn & hf
        push = both
        pos = jnp.where(push, st["sp"], S)
        stack = stack.at[lanes, pos].set(far, mode="drop"); sentry = sentry.at[lanes, pos].set(ef, mode="drop")
        sp = st["sp"] + push.astype(I32)
        one = visit & (hn | hf)
        nxt_node = jnp.where(hn, near, far); nxt_entry = jnp.where(hn, en, ef)
        open_leaf = visit & leaf
        st["lp"] = jnp.where(open_leaf, meta[:, 2], st["lp"]); st["le"] = jnp.where(open_leaf, meta[:, 2] + meta[:, 3], st["le"])
        one = mat(one)
        need_pop = go & ~one
        can = need_pop & (sp > 0)
        top = stack[lanes, jnp.maximum(sp - 1, 0)]; tent = sentry[lanes, jnp.maximum(sp - 1, 0)]
        st["node"] = jnp.where(one, nxt_node, jnp.where(can, top, jnp.where(need_pop, -1, st["node"])))
        st["entry"] = jnp.where(one, nxt_entry, jnp.where(can, tent, st["entry"]))
        st["sp"] = sp - can.astype(I32)
        # prim phase
        inl = st["lp"] < st["le"]
        rows = jax.vmap(lambda s: jax.lax.dynamic_slice_in_dim(slot_tab, s, W, 0))(mat(jnp.where(inl, st["lp"], 0)))
        tt, uu, vv = moller_trumbore_edges(rows[:, :, 0:3], rows[:, :, 3:6], rows[:, :, 6:9], o[:, None], d[:, None])
        pid = jax.lax.bitcast_convert_type(rows[:, :, 9], I32)
        bt, bp = st["t"], st["prim"]
        for i in range(W):
            ok = inl & (st["lp"] + i < st["le"]) & (tt[:, i] > 0) & ((tt[:, i] < bt) | ((tt[:, i] == bt) & (pid[:, i] < bp)))
            bt = jnp.where(ok, tt[:, i], bt); bp = jnp.where(ok, pid[:, i], bp)
        st["t"], st["prim"] = bt, bp
        st["lp"] = jnp.where(inl, jnp.minimum(st["lp"] + W, st["le"]), st["lp"])
        return st, stack, sentry
    def body(c):
        st, stack, sentry, out_t, out_p, nxt = refill(c)
        st, stack, sentry = jax.lax.fori_loop(0, ITERS, step, (st, stack, sentry))
        return st, stack, sentry, out_t, out_p, nxt
    def cond(c):
        st, *_, nxt = c
        return jnp.any(st["ray"] >= 0) | (nxt < R)
    c = jax.lax.while_loop(cond, body, (st, stack, sentry, out_t, out_p, I32(0)))
    return c[3][:R], c[4][:R]

tri = load_triangles("bunny")
tree, _ = jaxbvh.load(DATA / "trees" / "bunny_binned_ref.npz")
sets = [("bunny random", tree, tri, *rays.make_rays(jax.random.key(0), "random", tree, tri, 16384)),
        ("bunny bounce", tree, tri, *rays.make_rays(jax.random.key(0), "bounce", tree, tri, 16384))]
rng = np.random.default_rng(0)
ctri = tri[np.sort(rng.choice(len(tri), 6320, replace=False))]
ct = chain_tree(ctri)
sets.append(("chain 6320", ct, ctri, *rays.make_rays(jax.random.key(1), "random", ct, ctri, 2048)))
for name, t, tr, o, d in (sets if len(sys.argv) == 1 else []):
    jt = to_jax(t)
    pk = pack(jt, jnp.asarray(tr), rays.intersect_triangle, 4)
    args = (pk.node, pk.slot_tri, jt.root, jnp.asarray(o), jnp.asarray(d))
    for S in ([64] if not name.startswith("chain") else [8192]):
        jax.block_until_ready(lean(*args, S=S))
        c = cpu(); res = jax.block_until_ready(lean(*args, S=S)); s = cpu() - c
        ref = rays.closest_hit(t, tr, o, d)
        c = cpu(); ref = rays.closest_hit(t, tr, o, d); s_ref = cpu() - c
        print(name, "lean rays/cpu-s", round(len(o) / s), "current", round(len(o) / s_ref),
              "same prim", float(np.mean(np.asarray(res[1]) == ref.prim)), flush=True)
if len(sys.argv) > 1:
    name, t, tr, o, d = sets[-1]
    jt = to_jax(t); pk = pack(jt, jnp.asarray(tr), rays.intersect_triangle, 4)
    args = (pk.node, pk.slot_tri, jt.root, jnp.asarray(o[:1024]), jnp.asarray(d[:1024]))
    jax.block_until_ready(lean(*args, S=8192))
    jax.profiler.start_trace("/tmp/raytrace", create_perfetto_trace=True)
    jax.block_until_ready(lean(*args, S=8192))
    jax.profiler.stop_trace()
    hlo = lean.lower(*args, S=8192).compile().as_text()
    open("/tmp/lean_hlo.txt", "w").write(hlo)
