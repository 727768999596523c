"""Simulation and map-making: a channel's inputs from the configuration (K/W, A_2, the
TES, the sky: :mod:`.channel_inputs`), the TOD of a detector pair (litebird_sim scanning, HWP,
dipole, noise; :mod:`.tod`, :mod:`.data_model`), the filters (HWP-harmonic removal, the
4 f_HWP notch, baselines), binned map-making and HWP demodulation, the TOD path per seed
(:mod:`.tod_maps`) and the map-domain path: one TOD pass per channel (:mod:`.fixed_maps`),
the filter as functions of multipole (:mod:`.filter_response`) and the seeds in the map
domain (:mod:`.map_domain`); and the per-(channel, seed) maps file.
"""
