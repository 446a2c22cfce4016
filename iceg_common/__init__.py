"""Shared root of the ICEG distribution: the exception hierarchy, SE(2) algebra, id sets and
the loading of numba's cached kernels (:mod:`iceg_common.numba_loading`) and of the scipy
modules their linear algebra calls (:mod:`iceg_common.scipy_lapack`).

``frontends`` and ``graph`` are leaves that must not import ``iceg`` or each other, yet the
project has one exception hierarchy and one set of SE(2) conventions. Both live here, in a
package with no project dependencies that every other package may import.
"""

from iceg_common.errors import ConfigError, GraphError, IcegError, LogFormatError

__all__ = ["ConfigError", "GraphError", "IcegError", "LogFormatError"]
