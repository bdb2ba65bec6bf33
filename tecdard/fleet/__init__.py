"""Many arms, as data: the roster and the Zenoh routers' access control it makes (acl), and every episode in
one store (episodes) with its Parquet index (index). The commands over them are the CLI's (tecdard.cli.fleet,
tecdard.cli.episodes), the router the runtime's (tecdard.runtime.router)."""
