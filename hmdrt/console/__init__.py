"""What a person at a terminal sees: logging configured once, and a status line while long work runs."""
