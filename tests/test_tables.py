import pytest

from kftrack.tables import Table


def test_plain_text_is_aligned_and_numbers_right_justified() -> None:
    t = Table([["CV", 12.3456], ["IMM", 8.9]], ["filter", "RMSE (m)"], formats=["", ".1f"])
    assert repr(t).splitlines() == ["filter  RMSE (m)", "------  --------", "CV          12.3", "IMM          8.9"]


def test_html_escapes_and_has_one_row_per_entry() -> None:
    t = Table([["a<b", 1], ["c", 2]], ["name", "n"], caption="x & y")
    h = t._repr_html_()
    assert h.count("<tr>") == 3 and "a&lt;b" in h and "<caption>x &amp; y</caption>" in h


@pytest.mark.parametrize("kwargs, match", [
    (dict(rows=[[1, 2, 3]], header=["a", "b"]), r"rows\[0\] has 3 values"),
    (dict(rows=[[1, 2]], header=["a", "b"], formats=[".1f"]), "formats must give one format per column"),
    (dict(rows=[], header=[]), "header must name"),
])
def test_bad_input_names_the_argument(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        Table(**kwargs)
