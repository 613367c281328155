"""mapservice: an event-sourced map and fleet-history service for factory robots.

This package holds what every component shares: the event model, the 2019 wire codec
and its validation, settings, the storage/broker/clock ports and their adapters.
The components live beside it: ``mapservice.ingest`` (``ingest/``),
``mapservice.processors`` (``processors/``) and ``mapservice.api`` (``api/``).
"""

__version__ = "0.1.0"
