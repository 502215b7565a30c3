"""The Zenoh router process (``service``) and its options (``options``)."""
