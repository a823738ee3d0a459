"""A run as one file and as a live stream for robotics tools: MCAP files and a Foxglove WebSocket
bridge (`topics`: what becomes which topic; `mcap_run`: the file; `live`: the bridge)."""
