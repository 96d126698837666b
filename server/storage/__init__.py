"""Where the service keeps things: the metadata database, its migrations, and the blob store."""
