"""The service layer: `rllock serve`, a Ray Serve application (batched network evaluation, a job queue,
an HTTP API and the web page in `web/`). It sits above the orchestration floor and below the command line.
"""
