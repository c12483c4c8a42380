"""Linear filters the identification core runs on records, imported when first used."""


def lfilter(b, a, x, axis=-1, zi=None):
    """
    Filter x by b / a along `axis` as scipy.signal.lfilter does (imported on first use).

    Importing scipy.signal costs about 0.85 s (scipy.stats comes with it); every `evaluate`,
    `fit` and node start paid it at import time for a filter a model runs only when fitted.
    """
    from scipy.signal import lfilter as scipy_lfilter
    return scipy_lfilter(b, a, x, axis=axis, zi=zi)
