"""How a PTM is told to a person: the report and its figures, numbers as read, and where the map is
unsure."""
