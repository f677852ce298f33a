"""Constants of the robust statistics shared by the filters, quality flags and fits of :mod:`flow`."""

from __future__ import annotations

#: Scale of the median absolute deviation to the standard deviation of normal data,
#: ``1 / Phi^-1(3/4)`` (rounded as usual): ``MAD_TO_SIGMA * MAD`` estimates sigma while one
#: outlier cannot move it.
MAD_TO_SIGMA = 1.4826
