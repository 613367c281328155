"""mapservice: an event-sourced map and fleet-history service for factory robots.

`core/` is the domain (pure), `adapters/` the outside world behind its ports, `sql/` the
analysts' SQL interface, `runtime/` what every process runs, `local/` and `bench/` the
tooling the product never imports. The components live beside this folder and are
installed inside it: ``mapservice.ingest`` (``ingest/``), ``mapservice.processors``
(``processors/``), ``mapservice.api`` (``api/``) and ``mapservice.robot`` (``robot/``).
The README's "Code layout" shows the tree; pyproject's import contracts pin it.
"""

__version__ = "0.1.0"
