"""
The node process: PiezoNode (the base of every node) and run_node (init, spin, clean shutdown).

Nodes stay thin: they declare parameters as `PARAMS` (nodes.params.ParamSpec), create their sample
streams with `sample_publisher` / `sample_subscription` (nodes.qos), convert messages with
nodes.wire, report health through nodes.diagnostics.Diagnostics, and start from `main_for`.
"""
from __future__ import annotations

import contextlib
import faulthandler
import signal
import sys
from typing import Callable, Sequence

import rclpy
import rclpy.task
from rclpy.node import Node
from rclpy.parameter_service import ParameterService
from rclpy.qos import QoSProfile
from sensor_msgs.msg import JointState

from piezo_narx_ros.errors import ConfigError, PiezoNarxError
from piezo_narx_ros.nodes.params import ParamSpec, declare_parameters, one_line
from piezo_narx_ros.nodes.qos import (SAMPLE_DEPTH, PublishFailures, QosWatch, qos_overriding,
                                      sample_qos)
from piezo_narx_ros.nodes.topics import DEFAULT_NAMESPACE

# Exit codes of a node process.
EXIT_OK = 0
EXIT_FAILURE = 1       # unexpected exception
EXIT_CONFIG = 2        # refused to start: bad parameter, missing model file, ...

# Signals that stop a node cleanly (SIGHUP: its terminal was closed).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
#: Longest a draining node (the recorder) keeps taking delivered messages after a stop signal (s),
#: and the quiet time that ends the drain sooner (s).
DRAIN_S = 2.0
DRAIN_QUIET_S = 0.2
#: Longest the teardown after the spin may take (s) before the process is ended, exit 1.
#: rclpy's and DDS's C teardown has deadlocked (a node destroyed inside Context.shutdown), and a
#: process hung there ignores SIGTERM and SIGINT: their handlers only set a flag that nothing
#: reads any more. faulthandler's watchdog thread needs no GIL and prints every thread's stack.
TEARDOWN_S = 20.0

#: rclpy's Node() and its parameter services create a node's first DDS entities. One of twelve
#: nodes started at once on one domain hung there for good (Fast DDS, in create_service; CI
#: 2026-12-03). In a node process each of these steps is bounded: past STARTUP_S the process
#: prints every thread's stack and exits 1, which a supervisor can restart; a hung one it cannot.
STARTUP_S = 60.0
_bound_startup = False    # set by run_node: a node made inside a test process is never ended


#: Environment and files by which a user configures Fast DDS; any of them: fastdds_profile
#: leaves Fast DDS alone.
FASTDDS_USER_SETTINGS = ('FASTDDS_DEFAULT_PROFILES_FILE', 'SKIP_DEFAULT_XML')
FASTDDS_CWD_PROFILE = 'DEFAULT_FASTDDS_PROFILES.xml'


def fastdds_profile(environ=None, cwd: str | None = None) -> str | None:
    """
    Point Fast DDS at config/fastdds.xml unless the user configured Fast DDS; return that path.

    Sets FASTDDS_DEFAULT_PROFILES_FILE in `environ` (default os.environ), before rclpy.init, and
    returns None without a change when one of FASTDDS_USER_SETTINGS is set, when `cwd` (default
    the working directory) holds DEFAULT_FASTDDS_PROFILES.xml, or when the file is not found. The
    profile keeps type information out of discovery: a participant destroyed while peers asked
    for it crashed in Fast DDS 3.2 (docs/nodes.md).
    """
    import os
    from pathlib import Path
    environ = os.environ if environ is None else environ
    if any(name in environ for name in FASTDDS_USER_SETTINGS):
        return None
    if (Path(cwd or os.getcwd()) / FASTDDS_CWD_PROFILE).is_file():
        return None
    from piezo_narx_ros.share import config_path
    try:
        path = str(config_path('fastdds.xml'))
    except ConfigError:
        return None
    environ['FASTDDS_DEFAULT_PROFILES_FILE'] = path
    return path


def make_executor(kind: str = 'events'):
    """
    Return the executor of a name.

    'events' -> rclpy.experimental.EventsExecutor (C++ event loop; pub->sub latency ~14 us here
    against ~92 us with the single-threaded executor), 'single' -> SingleThreadedExecutor.
    """
    if kind == 'events':
        from rclpy.experimental import EventsExecutor
        return EventsExecutor()
    if kind == 'single':
        from rclpy.executors import SingleThreadedExecutor
        return SingleThreadedExecutor()
    raise ConfigError(f"executor must be 'events' or 'single', got {kind!r}")


def run_node(node_cls: Callable[..., Node], args: list[str] | None = None,
             executor: str | None = None) -> int:
    """
    Run a node process: init, construct, spin, clean shutdown. Returns the exit code.

    SIGINT/SIGTERM/SIGHUP stop the spin and exit 0 (SIGHUP: the terminal was closed; a recorder
    must close its bag then, not die); a node that refuses to start (ConfigError or any
    PiezoNarxError from its constructor) prints one line `NAME: error: reason` and exits 2; any
    other exception exits 1. The executor is EventsExecutor unless PIEZO_NARX_EXECUTOR=single or
    `executor` says otherwise. A crash in compiled code (SIGSEGV, SIGBUS, ...) or SIGABRT prints
    every thread's Python stack to stderr first; so does a teardown step of rclpy or DDS that
    runs over TEARDOWN_S, and the process then exits 1.
    """
    import os
    import threading

    # A node has died in DDS's C code on the way out (exit -11: Fast DDS's TypeLookup thread
    # during the participant's teardown, docs/nodes.md): the stacks say where, and a supervisor
    # (or a test) that finds a node hung can send SIGABRT to get them. (Already on under pytest
    # or PYTHONFAULTHANDLER.)
    if not faulthandler.is_enabled():
        faulthandler.enable()

    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    if args is None:
        args = sys.argv
    kind = executor or os.environ.get('PIEZO_NARX_EXECUTOR', 'events')
    prog = getattr(node_cls, 'NODE_NAME', node_cls.__name__)
    stop = threading.Event()
    # Our own handlers only set a flag: the spin loop then ends between callbacks, so no callback
    # ever runs on a context that a signal has already shut down (rclpy's handlers do that, and
    # publish() in a running callback then fails). EventsExecutor.spin() also ignores shutdown.
    for sig in STOP_SIGNALS:
        signal.signal(sig, lambda *_: stop.set())
    code = EXIT_OK
    node = None
    started = None     # the node object, constructed or not (see _teardown)
    ex = None
    fastdds_profile()
    global _bound_startup
    _bound_startup = True
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    try:
        started = node_cls.__new__(node_cls)
        started.__init__()
        node = started
        check_overrides(node)
        ex = make_executor(kind)
        ex.add_node(node)
        paced = node.take_pacing() if isinstance(node, PiezoNode) else False
        timeout = 0.1
        # Unpaced nodes spin inside the executor for up to `timeout` per Python round: with
        # spin_once, every callback also paid a Python loop round (rclpy.ok(), the stop flag):
        # measured 38 -> 31 % of a core for the estimator at 20 kHz in batches of 20. A future
        # that completes only on finish() makes spin_until_future_complete a spin with a timeout.
        finished = rclpy.task.Future()   # completed by PiezoNode.finish(), else never
        if isinstance(node, PiezoNode):
            node._finished = finished
        while not stop.is_set() and rclpy.ok() and not finished.done():
            if paced:
                ex.spin_once(timeout_sec=timeout)
                if not stop.is_set():
                    timeout = node.pace()
            else:
                ex.spin_until_future_complete(finished, timeout_sec=timeout)
        if stop.is_set() and isinstance(node, PiezoNode) and node.drain_count() is not None:
            _drain(ex, node)
    except (KeyboardInterrupt, ExternalShutdownException):
        code = EXIT_OK
    except PiezoNarxError as exc:
        print(f'{prog}: error: {one_line(exc)}', file=sys.stderr, flush=True)
        code = EXIT_CONFIG
    except Exception as exc:  # noqa: BLE001 - last resort: one line, non-zero
        print(f'{prog}: error: {type(exc).__name__}: {one_line(exc)}', file=sys.stderr,
              flush=True)
        code = EXIT_FAILURE
    finally:
        _teardown(ex, node, started)
    return code


@contextlib.contextmanager
def _bounded(seconds: float):
    """End the process (exit 1, every thread's stack on stderr) if the block runs over seconds."""
    faulthandler.dump_traceback_later(seconds, exit=True)
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()


def _startup_step():
    """Bound a DDS start-up step by STARTUP_S in a node process (run_node), else nothing."""
    return _bounded(STARTUP_S) if _bound_startup else contextlib.nullcontext()


def _teardown(ex, node, started=None) -> None:
    """
    Shut the executor down, close and destroy the node, shut rclpy down.

    rclpy's and DDS's steps are bounded by TEARDOWN_S each; the node's close() is not: a
    recorder there writes its queue and its bag's summary, which a watchdog must not cut short.
    `started`: the node object whose constructor raised (node None), destroyed here, after its
    refusal was printed and before rclpy's shutdown. Left to rclpy.try_shutdown, it would be
    destroyed while the context shuts down, where a teardown step that asks the context
    anything deadlocks (measured: rclpy.ok() in a node's destroy_node).
    """
    if ex is not None:
        with _bounded(TEARDOWN_S):
            ex.shutdown()
    if node is not None:
        try:
            node.close()  # node-specific cleanup hook (see PiezoNode)
        except Exception:  # noqa: BLE001 - never mask the real exit reason
            pass
    with _bounded(TEARDOWN_S):
        if node is not None:
            node.destroy_node()
        elif started is not None:
            try:
                started.destroy_node()
            except Exception:  # noqa: BLE001 - raised before Node.__init__: nothing to destroy
                pass
        rclpy.try_shutdown()


# Parameters replaced by the standard QoS overrides (issue 10): refused with the new name rather
# than silently ignored, since a user who sets them expects a QoS change.
RETIRED_QOS_PARAMETERS = ('best_effort', 'qos_depth', 'depth')


def refuse_retired(node: Node) -> None:
    """Raise ConfigError naming a retired QoS parameter given to `node` (and its replacement)."""
    given = getattr(node, '_parameter_overrides', {})   # rclpy keeps no public copy
    retired = sorted(n for n in given if n in RETIRED_QOS_PARAMETERS and not node.has_parameter(n))
    if retired:
        raise ConfigError(f'parameter {retired[0]} no longer exists: QoS is set with the standard '
                          'overrides, e.g. -p qos_overrides./piezo/deflection.publisher.'
                          'reliability:=best_effort or ...depth:=20000 (docs/nodes.md)')


def check_overrides(node: Node) -> None:
    """
    Refuse retired QoS parameters with a hint.

    Warn about other parameters that were given but that `node` does not declare (ROS 2 ignores
    them silently; a typo then looks like a setting that took effect).
    """
    refuse_retired(node)
    given = set(getattr(node, '_parameter_overrides', {}))   # rclpy keeps no public copy
    declared = {name for name in given if node.has_parameter(name)}
    pending = node.pending_parameter_prefixes() if hasattr(
        node, 'pending_parameter_prefixes') else []
    unknown = sorted(n for n in given - declared if not any(n.startswith(p) for p in pending))
    if unknown:
        node.get_logger().warning(f'ignoring unknown parameter(s): {", ".join(unknown)}')


def _drain(ex, node: PiezoNode) -> None:
    """
    Take the messages DDS already delivered to `node` before it closes.

    A stop signal ends the spin between callbacks; what was published just before it still waits
    in the reader's queue (measured under load: 180 of 600 samples). Spins until
    `node.drain_count()` has not moved for DRAIN_QUIET_S, at most DRAIN_S.
    """
    import time
    now = time.monotonic()
    end, last, since = now + DRAIN_S, node.drain_count(), now
    while now < end and now - since < DRAIN_QUIET_S:
        ex.spin_once(timeout_sec=0.02)
        now, count = time.monotonic(), node.drain_count()
        if count != last:
            last, since = count, now


def main_for(node_cls) -> Callable[[list[str] | None], None]:
    """Return the `main` of a console script: it exits the process with run_node's code."""
    def main(args: list[str] | None = None) -> None:
        sys.exit(run_node(node_cls, args))
    return main


def _warm_codec(msg_type) -> None:
    """Load the batch codec's compiled kernels before a batch stream's first message."""
    if msg_type is not JointState:
        from piezo_narx_ros.nodes.wire import warm_up
        warm_up()


class PiezoNode(Node):
    """
    Node base.

    Default namespace `piezo` (a `__ns:=` remap still wins), `close()` hook called once on
    shutdown, and start-up parameters declared from `PARAMS` (a list of ParamSpec).
    """

    NODE_NAME = 'piezo_node'
    PARAMS: Sequence[ParamSpec] = ()

    def __init__(self, **kwargs):
        kwargs.setdefault('namespace', DEFAULT_NAMESPACE)
        # The parameter services (12 DDS endpoints) are made once the parameters are accepted:
        # a node that refuses its parameters creates a third of the entities, and is gone sooner.
        services = kwargs.pop('start_parameter_services', True)
        with _startup_step():
            super().__init__(self.NODE_NAME, start_parameter_services=False, **kwargs)
        self._finished = None     # run_node's future: finish() completes it
        self.qos_watch = QosWatch(self)
        self.publish_failures = PublishFailures(self.get_logger())
        self.params = declare_parameters(self, self.PARAMS)
        # Before the node opens anything: a refused recorder left an empty bag behind.
        refuse_retired(self)
        if services:
            with _startup_step():
                self._parameter_service = ParameterService(self)   # rclpy's own attribute

    def finish(self) -> None:
        """
        End run_node's spin after this callback; the process then exits 0.

        For nodes that are done on their own (the player at the bag's end). Shutting the context
        down from a callback instead raced the executor, which still spun on it (exit 1 about
        once in 8 runs).
        """
        if self._finished is not None and not self._finished.done():
            self._finished.set_result(True)

    def drain_count(self) -> int | None:
        """
        Messages taken so far, for a node that drains its queues on a stop signal; None: no drain.

        The recorder drains (a closed terminal must not cost the samples already delivered);
        nodes that compute and publish stop at once.
        """
        return None

    def sample_publisher(self, topic: str, msg_type=JointState, depth: int = SAMPLE_DEPTH,
                         qos: QoSProfile | None = None):
        """
        Create the publisher of a per-sample stream.

        `sample_qos` (or `qos`, e.g. a bag's recorded profile), the standard QoS overrides, and
        incompatible-QoS reporting (QosWatch).
        """
        _warm_codec(msg_type)
        pub = self.create_publisher(msg_type, topic, qos or sample_qos(depth),
                                    qos_overriding_options=qos_overriding(),
                                    event_callbacks=self.qos_watch.callbacks('publisher', topic))
        self.qos_watch.add('publisher', pub)
        self.publish_failures.guard(pub)      # a refused write loses a sample, not the node
        return pub

    def sample_subscription(self, topic: str, callback, msg_type=JointState, raw: bool = True,
                            depth: int = SAMPLE_DEPTH):
        """
        Create the subscription to a per-sample stream (raw CDR bytes by default).

        With the same QoS handling as `sample_publisher`.
        """
        _warm_codec(msg_type)
        sub = self.create_subscription(
            msg_type, topic, callback, sample_qos(depth), raw=raw,
            qos_overriding_options=qos_overriding(),
            event_callbacks=self.qos_watch.callbacks('subscription', topic))
        self.qos_watch.add('subscription', sub)
        return sub

    def pending_parameter_prefixes(self) -> list[str]:
        """
        Return the prefixes of parameters declared later than construction.

        QoS overrides of subscriptions made on demand; run_node does not call them unknown.
        """
        return []

    def take_pacing(self) -> bool:
        """
        Return True to be paced by run_node's loop instead of by a timer (default False).

        Such a node does its due work in `pace()`, which run_node calls after every spin_once,
        and says there how long the loop may wait for callbacks. At 2 kHz an rclpy timer alone
        cost ~110 us of CPU and 4 context switches per tick here; paced this way, the command
        node went from 45-50 % to 38 % of a core.
        """
        return False

    def pace(self) -> float:
        """Do the work due now; return the seconds until more is due (see take_pacing)."""
        return 0.1

    def close(self) -> None:
        """Release resources (files, sockets); called once by run_node before destroy_node."""
