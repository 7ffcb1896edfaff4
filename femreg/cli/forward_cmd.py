"""``femreg forward``: solve a forward (ground-truth) elasticity model and save it.

Example: ``femreg forward 3d --inclusion-modulus 40 -o out/hi3d.npz`` (``.vtu`` also writes a ParaView file).
Prints DOFs, wall time per stage and peak memory.
"""
from __future__ import annotations

import resource
import time


def add_parser(subparsers):
    p = subparsers.add_parser("forward", help="solve a forward elasticity model (ground truth) and save it",
                              description=__doc__.splitlines()[0])
    p.add_argument("model", choices=["plane-strain", "plane-stress", "3d"])
    p.add_argument("-o", "--output", default=None, help="output file (.npz reloadable, .vtu for ParaView); "
                                                         "default forward_<model>.npz")
    p.add_argument("--inclusion-modulus", type=float, default=40.0, help="MPa (default 40, HI)")
    p.add_argument("--background-modulus", type=float, default=10.0, help="MPa (default 10)")
    p.add_argument("--poisson", type=float, default=0.495)
    p.add_argument("--block-mm", type=float, default=160.0)
    p.add_argument("--inclusion-diameter-mm", type=float, default=15.0)
    p.add_argument("--inclusion-depth-mm", type=float, default=30.0)
    p.add_argument("--patch-mm", type=float, default=50.0, help="compression patch width, mm; 0 = whole top face")
    p.add_argument("--compression-mm", type=float, default=1.0)
    p.add_argument("--mesh-size-mm", type=float, default=None, help="element size in the imaged region, mm")
    p.add_argument("--coarse-size-mm", type=float, default=None, help="element size far away, mm")
    p.add_argument("--symmetry", choices=["quarter", "half", "full"], default="quarter", help="3D only")
    p.add_argument("--solver", choices=["auto", "pardiso", "superlu"], default="auto")
    p.add_argument("--cache", action="store_true", help="use the forward-solution disk cache")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    import forward

    t0 = time.perf_counter()
    sol = forward.solve_elasticity(
        args.model, inclusion_modulus=args.inclusion_modulus, background_modulus=args.background_modulus,
        poisson=args.poisson, block_mm=args.block_mm, inclusion_diameter_mm=args.inclusion_diameter_mm,
        inclusion_depth_mm=args.inclusion_depth_mm, patch_mm=None if args.patch_mm == 0 else args.patch_mm,
        compression_mm=args.compression_mm, mesh_size_mm=args.mesh_size_mm, coarse_size_mm=args.coarse_size_mm,
        symmetry=args.symmetry, solver=args.solver, cache=args.cache)
    out = args.output or f"forward_{args.model}.npz"
    path = sol.save(out)
    i = sol.info
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if "from_cache" in i:
        print(f"loaded from cache {i['from_cache']}")
    print(f"{args.model}: {i['n_dofs']} DOFs ({i['n_elements']} P2 elements), mesh {i['mesh_time_s']:.1f} s, "
          f"assembly {i['assembly_time_s']:.1f} s, solve {i['solve_time_s']:.1f} s ({i['solver']}), "
          f"total {time.perf_counter() - t0:.1f} s, peak memory {peak:.0f} MB, "
          f"reaction force {i['reaction_force']:.3f} {'N' if args.model == '3d' else 'N/mm'}")
    print(f"saved {path}")
    return 0
