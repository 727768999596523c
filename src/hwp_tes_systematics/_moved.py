"""The modules that moved into subpackages (after 0.1.0), still importable by their old names
with a DeprecationWarning: ``import hwp_tes_systematics.tod`` gives
``hwp_tes_systematics.simulation.tod``, the same module object."""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

MOVED = {
    "hwp_power": "instrument.hwp_power",
    "radiometry": "instrument.radiometry",
    "tes": "instrument.tes",
    "nonlinearity": "instrument.nonlinearity",
    "channel_inputs": "simulation.channel_inputs",
    "data_model": "simulation.data_model",
    "tod": "simulation.tod",
    "notch": "simulation.notch",
    "hwpss_removal": "simulation.hwpss_removal",
    "baselines": "simulation.baselines",
    "mapmaking": "simulation.mapmaking",
    "demodulation": "simulation.demodulation",
    "tod_maps": "simulation.tod_maps",
    "map_domain": "simulation.map_domain",
    "maps_file": "simulation.maps_file",
    "spectral": "simulation.spectral",
    "hilc": "analysis.hilc",
    "spectra": "analysis.spectra",
    "ilc_residuals": "analysis.ilc_residuals",
    "likelihood": "analysis.likelihood",
    "requirement": "analysis.requirement",
    "consistency": "analysis.consistency",
    "systematics": "analysis.systematics",
}
PACKAGE = __name__.rpartition(".")[0]


class _MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds ``PACKAGE.<old name>`` and loads it as the module at its new place."""

    def find_spec(self, fullname, path=None, target=None):
        package, _, name = fullname.rpartition(".")
        if package != PACKAGE or name not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        new_name = f"{PACKAGE}.{MOVED[spec.name.rpartition('.')[2]]}"
        warnings.warn(
            f"{spec.name} moved to {new_name}; import it from there",
            DeprecationWarning,
            stacklevel=3,
        )
        return importlib.import_module(new_name)

    def exec_module(self, module):
        """The module is the new one, already executed."""


def install() -> None:
    """Put the finder on sys.meta_path once."""
    if not any(isinstance(finder, _MovedModuleFinder) for finder in sys.meta_path):
        sys.meta_path.append(_MovedModuleFinder())
