"""From maps to the requirement: the harmonic ILC (:mod:`.hilc`), masks and pseudo-C_ell
(:mod:`.spectra`), the residual of each realization at any sigma_g1
(:mod:`.ilc_residuals`, :mod:`.systematics`), the likelihood of r (:mod:`.likelihood`)
and its consistency with the data (:mod:`.consistency`), delta r versus sigma_g1 and
the requirement (:mod:`.requirement`).
"""
