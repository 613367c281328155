"""The domain, as pure functions and frozen values: no I/O, no adapters, no settings.

Events and their identities (`events`), the 2019 wire codec and its validation (`wire2019`),
the 2019 query semantics (`legacy_query`), time travel (`timetravel`), conflicts
(`conflicts`), the live views' rules (`liveview`), live-stream messages (`live_messages`),
rendering chunks to pictures (`render`), and the ports the adapters implement (`ports`).
May import: only `mapservice.core` and third-party value libraries (msgspec, numpy, Pillow).
"""
