"""scipy's BLAS and LAPACK modules loaded without the rest of ``scipy.linalg``
(``iceg_common.scipy_lapack``): numba's linear algebra gives numpy's results, the package is
imported only where something asks for it, and then holds the modules as attributes.

Each case runs in a fresh interpreter: the test process has loaded these modules already."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_LINALG_KERNEL = """
import numba
import numpy as np

@numba.njit(cache=False)
def solved(a, b):
    return np.linalg.solve(a, b), np.linalg.inv(a)

a = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.25], [0.5, 0.25, 2.0]])
b = np.array([1.0, -2.0, 0.5])
got = solved(a, b)
want = (np.linalg.solve(a, b), np.linalg.inv(a))
agree = all(np.allclose(g, w, rtol=1e-12, atol=0.0) for g, w in zip(got, want, strict=True))
"""


def _run(*parts: str) -> dict[str, object]:
    """Run the script of ``parts`` (each dedented) in a fresh interpreter at the repository
    root; its last stdout line is a JSON object."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, "-c", "\n".join(textwrap.dedent(part) for part in parts)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    out: dict[str, object] = json.loads(proc.stdout.strip().splitlines()[-1])
    return out


def test_kernels_solve_with_the_preloaded_modules_and_the_package_attaches_them() -> None:
    out = _run(
        """
        import json, sys
        import iceg_common.numba_loading  # every kernel module imports it first
        from iceg_common import scipy_lapack
        loaded = all(name in sys.modules for name in scipy_lapack.SUBMODULES)
        before = "scipy.linalg" in sys.modules
        """,
        _LINALG_KERNEL,
        """
        after_kernel = "scipy.linalg" in sys.modules
        import scipy.linalg
        attached = [
            getattr(scipy.linalg, name.rpartition(".")[2]) is sys.modules[name]
            for name in scipy_lapack.SUBMODULES
        ]
        print(json.dumps({
            "preloaded": scipy_lapack.preload(),
            "loaded": loaded,
            "package_before": before,
            "package_after_kernel": after_kernel,
            "agree": agree,
            "attached": attached,
            "loader": type(scipy.linalg.__loader__).__name__,
            "spec_loader": type(scipy.linalg.__spec__.loader).__name__,
            "finders_left": [type(f).__name__ for f in sys.meta_path].count("_AttachToPackage"),
            "solve": scipy.linalg.solve([[2.0]], [4.0]).tolist(),
        }))
        """,
    )
    assert out["preloaded"] is True
    assert out["loaded"] is True
    # numba's registry and the kernel's LAPACK calls did not import the package
    assert out["package_before"] is False
    assert out["package_after_kernel"] is False
    assert out["agree"] is True
    # imported later, the package holds the preloaded modules and keeps its own loader
    assert out["attached"] == [True, True]
    assert out["loader"] == out["spec_loader"] == "SourceFileLoader"
    assert out["finders_left"] == 0
    assert out["solve"] == [2.0]


def test_nothing_is_preloaded_where_the_package_is_imported_already() -> None:
    out = _run(
        """
        import json, sys
        import scipy.linalg
        finders = len(sys.meta_path)
        from iceg_common import scipy_lapack
        print(json.dumps({
            "preloaded": scipy_lapack.preload(),
            "finders_added": len(sys.meta_path) - finders,
        }))
        """
    )
    assert out == {"preloaded": False, "finders_added": 0}


def test_a_module_that_cannot_be_loaded_leaves_the_package_to_numba() -> None:
    # LAPACK's module is not found: BLAS's, loaded before it, is taken out again, and numba
    # imports both through the package as it would without the preload.
    out = _run(
        """
        import importlib.machinery, json, sys
        find_spec = importlib.machinery.PathFinder.find_spec

        def without_lapack(name, path=None, target=None):
            if name == "scipy.linalg.cython_lapack":
                return None
            return find_spec(name, path, target)

        importlib.machinery.PathFinder.find_spec = without_lapack
        from iceg_common import scipy_lapack
        preloaded = scipy_lapack.preload()
        importlib.machinery.PathFinder.find_spec = find_spec
        left = [name for name in scipy_lapack.SUBMODULES if name in sys.modules]
        finders = [type(f).__name__ for f in sys.meta_path].count("_AttachToPackage")
        """,
        _LINALG_KERNEL,
        """
        print(json.dumps({
            "preloaded": preloaded,
            "left": left,
            "finders": finders,
            "agree": agree,
            "package": "scipy.linalg" in sys.modules,
        }))
        """,
    )
    assert out == {"preloaded": False, "left": [], "finders": 0, "agree": True, "package": True}
