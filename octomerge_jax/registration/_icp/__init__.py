"""Point-to-point ICP (thesis §3.3.1, §6.3, Alg. 3, eq. 3.18; Besl & McKay 1992): jitted,
batched over pairs or initial guesses, and differentiable by implicit differentiation at the
fixed point. Anderson-accelerated (Walker & Ni 2011; AA-ICP, Pavlov et al. 2018).

Modules: ``_single`` (``icp``, ``icp_padded``, ``icp_padded_stack``, ``icp_with_path``), ``_multi``
(``icp_multi``), ``_loop`` (the iteration and its typed state), ``_kabsch`` (the closed-form
step and the implicit derivative), ``_anderson``, ``_schedule`` (stages, table sizes,
hypotheses), ``_coarse`` (coarse query clouds), ``_centred``, ``_host``, ``_result``.
"""

from ._coarse import COARSE_MATCHING
from ._host import pad_points, pad_points_host
from ._kabsch import kabsch
from ._loop import IcpPath
from ._multi import icp_multi, sequential_default
from ._result import IcpMultiResult, IcpResult, invert_result
from ._schedule import default_hypotheses, stage_distances
from ._single import icp, icp_padded, icp_padded_stack, icp_with_path

__all__ = ["COARSE_MATCHING", "IcpMultiResult", "IcpResult", "default_hypotheses", "icp", "icp_multi",
           "icp_padded", "kabsch", "icp_padded_stack", "invert_result", "pad_points", "pad_points_host",
           "sequential_default", "stage_distances", "IcpPath", "icp_with_path"]
