"""
Export of an identified model to code that runs where the rig's real-time loop runs.

`write_c(model, directory)` (writer.py) writes pnr_model.h / pnr_model.c (C99, no allocation,
libm only, the weights as constants): the model's free run (`pnr_step`), its state-setting entry
points and the bounded one-sample inverse of controller_node's `inverse` mode
(`pnr_inverse_step`). The family-specific C comes from the family's own emitter
(`model.c_emitter()`, e.g. ident/narx/export.py); c_code.py holds what they share, c_inverse.py
the family-independent inverse. docs/export.md shows how to use the files.
"""
from piezo_narx_ros.errors import PiezoNarxError


class ExportError(PiezoNarxError):
    """A model cannot be exported (family without an emitter, missing sample rate, ...)."""
