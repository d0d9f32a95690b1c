"""The method, free of Hydra and run folders: typed options and their rules, checks, build
(scene + options -> discrete problem), reconstruct (levels, weight selection, camera
refinement and capture calibration, photometry, debias, absorption, joint frames).

The package is also the API's ``fit`` (:func:`flamerecon.fit.reconstruct.fit`): the two share
the name ``flamerecon.fit``, and Python's import system binds that name to the package, so
calling the package calls the function: ``fr.fit(setup, options)``."""

from __future__ import annotations

import inspect
import sys
import types


class CallablePackage(types.ModuleType):
    """This package, callable as :func:`flamerecon.fit.reconstruct.fit`."""

    def __call__(self, *args, **kwargs):
        from flamerecon.fit.reconstruct import fit

        return fit(*args, **kwargs)

    @property
    def __signature__(self) -> inspect.Signature:
        from flamerecon.fit.reconstruct import fit

        return inspect.signature(fit)


sys.modules[__name__].__class__ = CallablePackage
