"""
What a node learns about its peers from the ROS graph, and one log line per new problem.

Kept out of the shared plumbing (nodes.qos, params, codec, diagnostics, runtime); every check
here is cheap enough for a 1 Hz diagnostics tick.
"""
from __future__ import annotations


def same_name_count(node) -> int:
    """
    Count the nodes in the graph with this node's name and namespace, itself included.

    ROS 2 lets two nodes share a name; their publishers then feed the same topics and a parameter
    or service call reaches either one. 1 is the healthy value.
    """
    me = (node.get_name(), node.get_namespace())
    return max(1, sum(1 for entry in node.get_node_names_and_namespaces() if tuple(entry) == me))


def same_name_problem(node, topic: str | None = None) -> str | None:
    """
    One phrase when another node of the same name runs, else None.

    topic: the node's own output topic, named in the phrase as the place where the two mix.
    """
    n = same_name_count(node)
    if n < 2:
        return None
    where = f': their samples interleave on {node.resolve_topic_name(topic)}' if topic else ''
    return (f'{n} nodes named {node.get_fully_qualified_name()} are running{where}; stop one or '
            'give each its own name (--ros-args -r __node:=NAME)')


class EpisodeLog:
    """
    Log a problem once when it starts (at `level`) and once when it ends, not on every tick.

    `update(key, line)`: key None means no problem; a new non-None key logs `line`.
    `status(level, message)`: the same for a /diagnostics status at `threshold` or worse, keyed
    by the message's first two words (the counts in it change from tick to tick).
    """

    def __init__(self, logger, level: str = 'error'):
        self._log = getattr(logger, level)
        self._info = logger.info
        self._key = None

    def update(self, key, line: str = '', cleared: str = '') -> None:
        """Report `line` when `key` changes to a new problem; `cleared` when it goes away."""
        if key == self._key:
            return
        if key is not None:
            self._log(line)
        elif cleared:
            self._info(cleared)
        self._key = key

    def status(self, level: int, message: str, threshold: int = 2) -> None:
        """Log an ERROR (threshold 2) status once per episode; say when it is over."""
        key = ' '.join(message.split()[:2]) if level >= threshold else None
        self.update(key, message, 'ok again' if self._key is not None else '')
