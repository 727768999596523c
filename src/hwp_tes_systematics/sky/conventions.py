"""Conventions shared by every map of :mod:`hwp_tes_systematics.sky` (see the package
docstring): K_CMB, (I, Q, U), polarisation angle in the COSMO convention."""

MAP_UNIT = "K_CMB"
# Polarisation convention of every map made, written or read in the package: COSMO, the
# one healpy's spin-2 transforms and litebird_sim's data model assume. The IAU convention
# counts the polarisation angle the other way: U of opposite sign (POLCCONV = 'IAU' on input).
POLARISATION_CONVENTION = "COSMO"
N_STOKES = 3
