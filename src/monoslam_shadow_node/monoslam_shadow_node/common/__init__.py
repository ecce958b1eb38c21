"""What the three nodes share: the message layer, frame pairing and log notices."""
