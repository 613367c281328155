"""The MQTT-to-Kafka gateway: 2019 messages in, validated immutable events or dead letters
with reasons out, each MQTT message acknowledged only after Kafka has its record.

May import: `mapservice.core`, `adapters`, `runtime`, `settings`.
"""
