"""Topic names of the sample streams and the default namespace (relative; DESIGN.md "Topics")."""

TOPIC_COMMAND = 'voltage_command'
TOPIC_DEFLECTION = 'deflection'
TOPIC_ESTIMATE = 'deflection_estimate'
TOPIC_REFERENCE = 'position_reference'
TOPIC_DIAGNOSTICS = '/diagnostics'
DEFAULT_NAMESPACE = 'piezo'
