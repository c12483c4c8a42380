"""
The search's storage: one Optuna journal and one file per finished trial in the output folder.

A signal must not land inside a journal write. Optuna's file lock releases by renaming its lock
file; a KeyboardInterrupt between its steps leaves the lock held or ends in FileNotFoundError
instead of the interruption (seen in CI: SIGINT during `tell`). `SignalSafeJournal` holds SIGINT
and SIGTERM back while a write is under way and delivers them when it is done, so an interrupted
run always leaves a journal that `--resume` can read.
"""
from __future__ import annotations

import json
import os
import signal
import threading
import warnings
from contextlib import contextmanager
from pathlib import Path

from piezo_narx_ros.errors import ConfigError

STUDY_NAME = 'piezo-narx-search'
#: What the journal's study records about the run it belongs to (resume checks it).
FINGERPRINT_KEY = 'fingerprint'
_HELD = (signal.SIGINT, signal.SIGTERM)


def optuna_module():
    """Return optuna, quiet; ConfigError naming the pin when it is not installed."""
    try:
        import optuna
    except ImportError:
        raise ConfigError('the structure search needs Optuna: pip install the optuna pin of '
                          'requirements.txt, or fit with --preset envelope or paper') from None
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    warnings.filterwarnings('ignore', category=optuna.exceptions.ExperimentalWarning)
    return optuna


def sampler(optuna, seed: int, batch: int, batch_index: int):
    """Return batch `batch_index`'s TPE sampler, seeded from (seed, batch index)."""
    # Seeded per batch: a resumed run rebuilds batch b's sampler without the RNG state of the
    # process that asked batches 0..b-1 (the journal does not hold it).
    seed = (int(seed) * 1_000_003 + batch_index) % (2 ** 32)
    return optuna.samplers.TPESampler(seed=seed, multivariate=True, group=True,
                                      n_startup_trials=batch, constant_liar=True)


@contextmanager
def signals_held():
    """Hold SIGINT and SIGTERM back for the block; deliver the first one that came after it."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    previous = {s: signal.getsignal(s) for s in _HELD}
    for s in _HELD:
        signal.signal(s, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        if caught:
            signum = caught[0]
            handler = previous[signum]
            if callable(handler):
                handler(signum, None)
            elif handler == signal.SIG_DFL:
                os.kill(os.getpid(), signum)


def signal_safe_journal(path: str):
    """Return an Optuna JournalFileBackend on `path` whose writes are not cut by a signal."""
    from optuna.storages.journal import JournalFileBackend

    class SignalSafeJournal(JournalFileBackend):
        """The journal file, written whole or not at all whatever signal comes."""

        def append_logs(self, logs):
            with signals_held():
                super().append_logs(logs)

    return SignalSafeJournal(path)


class Study:
    """The Optuna study of one output folder: journal, trial files, resume."""

    def __init__(self, out: Path, resume: bool, force: bool):
        self.out = Path(out)
        self.journal = self.out / 'study.journal'
        self.trial_dir = self.out / 'trials'
        self.resume, self.force = resume, force

    def open(self, fp: str):  # noqa: A003 - pairs with the journal's lifetime
        """Create or load the study; refuse a resume of another run or a silent overwrite."""
        optuna = optuna_module()
        from optuna.storages import JournalStorage
        if self.resume and not self.journal.is_file():
            raise ConfigError(f'--resume: no study to continue in {self.out} (no '
                              f'{self.journal.name})')
        if not self.resume and self.journal.exists():
            if not self.force:
                raise ConfigError(f'{self.out} holds a search already ({self.journal.name}); '
                                  'continue it with --resume or start again with --force')
            self.journal.unlink()
            for p in sorted(self.trial_dir.glob('*')) if self.trial_dir.is_dir() else ():
                if p.is_file():
                    p.unlink()
        self.out.mkdir(parents=True, exist_ok=True)
        self.trial_dir.mkdir(exist_ok=True)
        storage = JournalStorage(signal_safe_journal(str(self.journal)))
        if self.resume:
            study = optuna.load_study(study_name=STUDY_NAME, storage=storage)
            if FINGERPRINT_KEY not in study.user_attrs and not study.get_trials(deepcopy=False):
                study.set_user_attr(FINGERPRINT_KEY, fp)    # cut right after it was created
            if study.user_attrs.get(FINGERPRINT_KEY) != fp:
                raise ConfigError(f'--resume: the study in {self.out} was run on other records '
                                  'or settings; give the same inputs and options, or start '
                                  'again with --force')
        else:
            study = optuna.create_study(study_name=STUDY_NAME, storage=storage,
                                        directions=['minimize', 'minimize'])
            study.set_user_attr(FINGERPRINT_KEY, fp)
        study.set_metric_names(['worst-case validation error', 'parameters'])
        self.study, self.optuna = study, optuna
        return study

    def trial_path(self, number: int) -> Path:
        """Return DIR/trials/NNNN.json (scores); its model is NNNN.model.json (+ .npz)."""
        return self.trial_dir / f'{number:04d}.json'

    def save_trial(self, number: int, params: dict, res) -> None:
        """Write a finished trial's scores and model (atomically: a crash leaves neither)."""
        from piezo_narx_ros.ident.model_io import save_model
        from piezo_narx_ros.ident.validation.report import json_safe
        if res.model is not None:
            save_model(res.model, self.trial_dir / f'{number:04d}.model.json',
                       metrics=res.scores, tests=res.tests)
        doc = {'trial': number, 'params': params, **res.to_dict()}
        path = self.trial_path(number)
        tmp = path.with_name(f'.{path.name}.{os.getpid()}.tmp')
        tmp.write_text(json.dumps(json_safe(doc), indent=1) + '\n')
        os.replace(tmp, path)

    def load_trial(self, number: int, params: dict, spec):
        """Return a trial finished on disk (scores and model), or None when it is not there."""
        from piezo_narx_ros.ident.model_io import load_model
        from piezo_narx_ros.ident.selection.experiment import CandidateResult
        path = self.trial_path(number)
        if not path.is_file():
            return None
        doc = json.loads(path.read_text())
        if doc.get('params') != params:
            return None
        res = CandidateResult(spec=spec, n_params=doc.get('n_params'),
                              scores=doc.get('scores') or {}, tests=doc.get('tests') or {},
                              validated=bool(doc.get('validated')),
                              fit_seconds=float(doc.get('fit_seconds') or 0.0),
                              error=doc.get('error'))
        model_path = self.trial_dir / f'{number:04d}.model.json'
        if res.error is None:
            if not model_path.is_file():
                return None
            res.model = load_model(model_path)
        return res
