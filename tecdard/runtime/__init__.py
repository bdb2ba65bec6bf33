"""The daemon process (`tecdard run`): its threads, its Zenoh interface, its recordings. It never imports a tool."""
