"""Every error of :mod:`foilc_hil.errors` and :mod:`drivers.errors` (the drive side's, re-exported by the former)
survives a pickle round trip (the demo's runs raise them in worker processes): same class, message, fields and the
``partial`` a failed run attaches.

The pickler here has its own, empty dispatch table: ``distributed`` (imported by other tests in the same process)
registers tblib's exception reducer in ``copyreg`` for every exception class that exists when it is imported, and
tblib's rebuild calls ``cls.__new__``, which for the drive's timeouts (a ``RuntimeError`` and a ``TimeoutError``)
is ``RuntimeError.__new__`` and refuses. A known limit: such an error cannot cross a Dask boundary; the robustness
tasks, the only Dask work, simulate and never raise it.
"""

from __future__ import annotations

import inspect
import io
import pickle

import pytest

import drivers.errors
import foilc_hil.errors as errors
from foilc_hil.io.mcap_log import LogWriteError

#: the errors whose constructor takes more than a message, with arguments
FIELDS: dict[type[BaseException], tuple[object, ...]] = {
    errors.EmergencyError: (0x2310, 0x03, "over-current"),
    errors.SdoError: (0x6060, 0, 0x06090030, "value range exceeded"),
}
CLASSES = [
    *sorted((cls for module in (errors, drivers.errors) for cls in vars(module).values()
             if inspect.isclass(cls) and issubclass(cls, errors.FoilcHilError) and cls.__module__ == module.__name__),
            key=lambda cls: cls.__name__),
    LogWriteError,
]


@pytest.mark.parametrize("cls", CLASSES, ids=lambda cls: cls.__name__)
def test_an_error_round_trips_through_pickle(cls: type[errors.FoilcHilError]) -> None:
    error = cls(*FIELDS.get(cls, ("the message",)))
    error.partial = {"trials": [1, 2]}
    buffer = io.BytesIO()
    pickler = pickle.Pickler(buffer)
    pickler.dispatch_table = {}  # the standard reduction, whatever copyreg holds (module docstring)
    pickler.dump(error)
    copy = pickle.loads(buffer.getvalue())
    assert type(copy) is cls and str(copy) == str(error) and copy.partial == {"trials": [1, 2]}
    assert vars(copy) == vars(error)
