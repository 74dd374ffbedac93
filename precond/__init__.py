"""precondition-service: verified action preconditions learned from demonstrations, as a service."""
