"""What every process runs around its component: logs, health (heartbeats, readiness
checks and their HTTP endpoint), the retry policy and start-up. No domain rules here.
May import: `mapservice.settings` and third-party libraries only.
"""
