"""What a process on a semmap bus needs: the Zenoh bus and its trust (bus), the service base classes every stage
runs in (service, stage_service), the router a run starts, the secure profile, health checks and the registry of
live runs. Nothing here knows what a landmark is."""
