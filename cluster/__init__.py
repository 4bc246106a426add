"""Ray cluster configuration and the job entry point for `ray submit` and Ray Jobs."""
