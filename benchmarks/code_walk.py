"""How far a reader walks to follow one image through ``PoseEstimator.estimate``.

The demo frame goes through the bundled estimator once per sampler while a profiler records
every call between two monose3 functions. The walk is the set of distinct caller -> callee
edges (a reader follows each once, however often a loop repeats it):

* rooms: the monose3 modules the walk visits;
* returns: edges that cross into a module the walk has already visited from elsewhere
  (each is a trip back to a file already read), listed by the module they return to.

    python benchmarks/code_walk.py [--samplers fit revdiff]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

import monose3
from monose3.api import ASSETS, estimate_pose, load_estimator
from monose3.data.inputs import load_camera, load_image, load_joints

PACKAGE_ROOT = Path(monose3.__file__).resolve().parent


def module_of(filename: str) -> str | None:
    """The package-relative module path of a source file, or None outside monose3."""
    path = Path(filename).resolve()
    return str(path.relative_to(PACKAGE_ROOT)) if path.is_relative_to(PACKAGE_ROOT) else None


def record_edges(run) -> list[tuple[str, str, str, str]]:
    """Distinct (caller module, caller function, callee module, callee function) in first-call order."""
    edges: dict[tuple[str, str, str, str], None] = {}

    def profile(frame, event, arg):
        if event != "call" or frame.f_back is None:
            return
        callee = module_of(frame.f_code.co_filename)
        caller = module_of(frame.f_back.f_code.co_filename)
        if callee and caller:
            edges[(caller, frame.f_back.f_code.co_name, callee, frame.f_code.co_name)] = None

    sys.setprofile(profile)
    try:
        run()
    finally:
        sys.setprofile(None)
    return list(edges)


def walk_figures(edges: list[tuple[str, str, str, str]]) -> dict:
    """Rooms visited and returns to a room already visited, from the walk's edges."""
    visited: set[str] = set()
    returns: Counter[str] = Counter()
    for caller, _, callee, _ in edges:
        visited.add(caller)
        if callee != caller:
            if callee in visited:
                returns[callee] += 1
            visited.add(callee)
    return {"rooms": len(visited), "returns": sum(returns.values()), "by_room": dict(returns.most_common())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samplers", nargs="+", default=["fit", "revdiff"])
    args = parser.parse_args()
    sample = ASSETS / "sample"
    image, camera = load_image(sample / "image.jpg"), load_camera(sample / "camera.json")
    estimator = load_estimator(None, robot="panda")
    joints = load_joints(sample / "joints.json", estimator.robot)
    for sampler in args.samplers:

        def estimate(sampler: str = sampler) -> None:
            estimate_pose(estimator, image, joints, camera.K, sampler=sampler)

        estimate()  # warm caches (meshes, renderer) so the walk is that of a steady-state image
        figures = walk_figures(record_edges(estimate))
        print(f"{sampler}: {figures['rooms']} rooms, {figures['returns']} returns")
        print("  returns by room: " + json.dumps(figures["by_room"]))


if __name__ == "__main__":
    main()
