"""The service's ``dsareg`` sub-commands (``subcommands``: serve, worker, submit) and the HTTP client (``client``)."""
