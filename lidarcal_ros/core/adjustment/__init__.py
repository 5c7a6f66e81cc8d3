"""The least-squares adjustment: normal equations, observability, strip blocks."""
