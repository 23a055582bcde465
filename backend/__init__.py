"""The cloud service: superset detection, margin crops, semantic verification, sessions for many vehicles."""
