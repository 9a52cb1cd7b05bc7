"""Bytes on the wire and files on disk: message schema, codec, framing, links,
and the pair-directory format shared by ground_sim and flight_sw."""
