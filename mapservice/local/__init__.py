"""The service on one machine, for development and demos only: the embedded brokers
(tansu, amqtt, Mosquitto), the process stack and its supervisor (`mapservice up`), the
demo's week of history, the Chromium the browser tests use, paths in a checkout.
Production never imports this package (an import-contract test checks it).
"""
