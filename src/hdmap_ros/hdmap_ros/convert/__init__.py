"""Pure conversions between messages (or message-like objects) and the core's data model."""
