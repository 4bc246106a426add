"""Ray cluster configuration and the job entry point for `ray submit` and Ray Jobs: files of the
repository that a cluster runs, not installed with the `rllock` package."""
