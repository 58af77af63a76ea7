"""controller_node package."""
