"""Tessera's side of its benchmarks against other renderers: a small server that `tessera bench`
starts and talks to in JSON lines, one request per line on stdin, one answer per line on stdout.

It drives Mitsuba 3 (pip install mitsuba==3.9.1, with Debian's libllvm19 and
DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so for its LLVM backend) and Embree 4
through the `embreex` package, so that the bench can time Tessera and its peer alternately in
one run, each loaded once. Requests:

  {"op": "probe", "module": "mitsuba" | "embreex"}      -> {"ok": true, "version": ...}
  {"op": "embree_load", "triangles": PATH, "rays": PATH} -> {"build_s": ...}
      PATH: little-endian float32; triangles 9 per triangle, rays 6 per ray (origin, direction)
  {"op": "embree_trace", "hits": PATH or null}            -> {"seconds": ..., "hits": ...}
      one closest-hit query per ray on one thread; PATH receives each ray's triangle (int32, -1: miss)
  {"op": "mitsuba_render", "scene": SCENE, "sampler": NAME, "spp": N, "seed": S, "threads": T,
   "out": PATH}                                          -> {"seconds": ..., "spp": ..., "width", "height"}
      SCENE: {"kind": "cornell"} (Mitsuba's own box) or {"kind": "gltf", "path": GLTF,
      "converter": gltf_to_mitsuba.py, "width": W, "height": H, "environment": [r, g, b],
      "camera": {"to_world": 4 x 4 rows, glTF's convention, "yfov_deg": F}};
      both with "max_depth" and "rr_depth". The scene is loaded, rendered once to warm up (the LLVM
      backend compiles its kernels then) and rendered again, timed; PATH receives the image as
      little-endian float32 RGB, rows from the top. With "passes": P (a reference), P renders of
      seeds S, S+1, ... are averaged, untimed warm-up left out.
Errors come back as {"error": "..."}; the server goes on.
"""
import json
import os
import sys
import tempfile
import time

_embree = {}
_converted = {}


def probe(req):
    module = req['module']
    if module == 'mitsuba':
        import drjit  # noqa: F401
        import mitsuba as mi
        mi.set_variant('llvm_ad_rgb')
        return {'ok': True, 'version': mi.__version__}
    if module == 'embreex':
        import embreex  # noqa: F401
        from embreex import rtcore_scene  # noqa: F401
        from importlib.metadata import version
        return {'ok': True, 'version': version('embreex')}
    raise ValueError('unknown module %r' % module)


def embree_load(req):
    import numpy as np
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh
    triangles = np.fromfile(req['triangles'], dtype='<f4').reshape(-1, 3, 3)
    rays = np.fromfile(req['rays'], dtype='<f4').reshape(-1, 6)
    t0 = time.perf_counter()
    scene = rtcs.EmbreeScene()
    mesh = TriangleMesh(scene, triangles)
    # Embree builds lazily, on the first query: one ray forces the build into this timing.
    scene.run(rays[:1, :3].copy(), rays[:1, 3:].copy())
    build = time.perf_counter() - t0
    _embree.update(scene=scene, mesh=mesh, origins=np.ascontiguousarray(rays[:, :3]),
                   directions=np.ascontiguousarray(rays[:, 3:]))
    return {'build_s': build, 'triangles': len(triangles), 'rays': len(rays)}


def embree_trace(req):
    import numpy as np
    e = _embree
    t0 = time.perf_counter()
    ids = e['scene'].run(e['origins'], e['directions'])
    seconds = time.perf_counter() - t0
    if req.get('hits'):
        np.asarray(ids, dtype='<i4').tofile(req['hits'])
    return {'seconds': seconds, 'hits': int((np.asarray(ids) >= 0).sum())}


def mitsuba_scene(desc, sampler, spp):
    import mitsuba as mi
    if desc['kind'] == 'cornell':
        d = mi.cornell_box()
        d['sensor']['film']['rfilter'] = {'type': 'box'}
        d['sensor']['sampler'] = {'type': sampler, 'sample_count': spp}
    elif desc['kind'] == 'gltf':
        key = (desc['path'], desc['width'], desc['height'])
        if key not in _converted:
            sys.path.insert(0, os.path.dirname(desc['converter']))
            import gltf_to_mitsuba
            outdir = tempfile.mkdtemp(prefix='tessera-mitsuba-')
            _converted[key] = (gltf_to_mitsuba, gltf_to_mitsuba.convert(
                desc['path'], outdir, width=desc['width'], height=desc['height'], filter='box',
                metal='principled'))
        module, d = _converted[key]
        d = json.loads(json.dumps(d))
        d['sensor']['sampler'] = {'type': sampler, 'sample_count': spp}
        camera = desc.get('camera')
        if camera:
            # Tessera's camera, glTF's convention (looking down -z, +x right) turned to Mitsuba's.
            import numpy as np
            m = np.array(camera['to_world'], dtype=np.float64) @ np.diag([-1.0, 1.0, -1.0, 1.0])
            d['sensor'].update({'type': 'perspective', 'fov': camera['yfov_deg'], 'fov_axis': 'y', 'to_world': m.tolist()})
        env = desc.get('environment')
        if env:
            d['environment'] = {'type': 'constant', 'radiance': {'type': 'rgb', 'value': env}}
        d['integrator'] = {'type': 'path', 'max_depth': desc['max_depth'], 'rr_depth': desc['rr_depth']}
        # Emission that came through a texture is left out, as Tessera's side leaves it out: the
        # texture masked it, and without it the factor alone would light the whole surface.
        import pygltflib
        gltf = pygltflib.GLTF2().load(desc['path'])
        textured = {'mat%d' % i for i, m in enumerate(gltf.materials or []) if m.emissiveTexture is not None}
        for shape in d.values():
            if isinstance(shape, dict) and shape.get('bsdf', {}).get('id') in textured:
                shape.pop('emitter', None)
        return module.load_scene(d)
    else:
        raise ValueError('unknown scene kind %r' % desc['kind'])
    d['integrator'] = {'type': 'path', 'max_depth': desc['max_depth'], 'rr_depth': desc['rr_depth']}
    return mi.load_dict(d)


def mitsuba_render(req):
    import drjit as dr
    import mitsuba as mi
    import numpy as np
    dr.set_thread_count(req['threads'])
    mi.set_variant('llvm_ad_rgb')
    mi.set_log_level(mi.LogLevel.Error)
    scene = mitsuba_scene(req['scene'], req['sampler'], req['spp'])
    spp = scene.sensors()[0].sampler().sample_count()
    passes = req.get('passes', 1)
    if passes == 1:
        np.array(mi.render(scene, spp=spp, seed=req['seed'] + 7919))  # warm-up: kernels compile here
    t0 = time.perf_counter()
    # A reference comes as several passes, averaged: one call's memory grows with spp x pixels.
    img = sum(np.array(mi.render(scene, spp=spp, seed=req['seed'] + k), dtype=np.float64) for k in range(passes))
    seconds = time.perf_counter() - t0
    rgb = np.ascontiguousarray(img[..., :3] / passes, dtype='<f4')
    spp *= passes
    rgb.tofile(req['out'])
    return {'seconds': seconds, 'spp': int(spp), 'width': rgb.shape[1], 'height': rgb.shape[0]}


OPS = {'probe': probe, 'embree_load': embree_load, 'embree_trace': embree_trace, 'mitsuba_render': mitsuba_render}


def main():
    for line in sys.stdin:
        if not line.strip():
            continue
        try:
            req = json.loads(line)
            answer = OPS[req['op']](req)
        except Exception as e:  # the bench prints it; the server takes the next request
            answer = {'error': '%s: %s' % (type(e).__name__, e)}
        sys.stdout.write(json.dumps(answer) + '\n')
        sys.stdout.flush()


if __name__ == '__main__':
    main()
