"""Reading results: `tj.RESULTS.message` and `.message()` on every container."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tippejax as tj
from tippejax._solution import result_message

LOST = tj.RESULTS.contact_lost
OK = tj.RESULTS.successful


def _text(item):
    # The enumeration's own table (equinox), independent of result_message.
    return tj.RESULTS[item]


def test_message_of_one_code():
    assert tj.RESULTS.message(OK) == "successful"
    assert tj.RESULTS.message(LOST) == _text(LOST) != ""
    assert isinstance(tj.RESULTS.message(LOST), str)
    code = int(np.asarray(LOST._value))
    assert tj.RESULTS.message(code) == _text(LOST)
    assert tj.RESULTS.message(np.int8(code)) == _text(LOST)


def test_message_elementwise_on_arrays_and_batched_codes():
    codes = np.array(
        [[0, int(np.asarray(LOST._value))], [int(np.asarray(LOST._value)), 0]], dtype=np.int8
    )
    out = tj.RESULTS.message(codes)
    assert isinstance(out, np.ndarray) and out.shape == (2, 2)
    assert out[0, 0] == out[1, 1] == "successful" and out[0, 1] == out[1, 0] == _text(LOST)
    batched = jax.vmap(lambda p: tj.RESULTS.where(p, LOST, OK))(jnp.array([True, False, True]))
    np.testing.assert_array_equal(
        tj.RESULTS.message(batched), [_text(LOST), "successful", _text(LOST)]
    )


def test_message_of_another_enumeration_uses_its_own_table():
    item = tj.FIT_RESULTS.max_steps_reached if hasattr(tj, "FIT_RESULTS") else None
    if item is None:
        pytest.skip("no FIT_RESULTS")
    assert tj.RESULTS.message(item) == tj.FIT_RESULTS[item]
    assert result_message(int(np.asarray(item._value)), tj.FIT_RESULTS) == tj.FIT_RESULTS[item]


@pytest.mark.parametrize(
    "bad, match",
    [
        (99, "lie in"),
        (-1, "lie in"),
        (np.array([0.5]), "integers"),
        ("x", "takes a result code"),
        (True, "takes a result code"),
    ],
)
def test_message_refuses_what_is_not_a_code(bad, match):
    with pytest.raises(ValueError, match=match):
        tj.RESULTS.message(bad)


def test_message_under_jit_says_to_read_it_outside():
    with pytest.raises(ValueError, match="outside jax.jit"):
        jax.jit(lambda c: tj.RESULTS.message(c))(jnp.int32(0))


def test_solution_and_batch_message():
    """Solution.message() on a single run (str) and on a batch (array), failures included."""
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 100.0)
    sol = tj.simulate(top, y0, 0.5, summary=True, max_steps=4, throw=False)
    assert sol.message() == tj.RESULTS.message(sol.result) == _text(tj.RESULTS.max_steps_reached)
    assert tj.RESULTS.message(sol) == sol.message()  # anything with a `result`
    batch = tj.simulate_batch(top, [0.1], [50.0, 100.0], 0.5, summary=True, max_steps=4)
    msgs = batch.message()
    assert msgs.shape == (1, 2)
    assert np.all(msgs == _text(tj.RESULTS.max_steps_reached))
    assert msgs[0, 1] == tj.RESULTS.message(batch.result)[0, 1]


def test_classify_refuses_a_dict():
    with pytest.raises(ValueError, match="classify takes a tippejax.TippeTop, got dict"):
        tj.classify({"A": 1.0, "C": 1.0})


def test_a_solution_prints_its_events_and_says_when_it_is_on_its_way():
    """`print(sol)` gives the level, result, events and outcome; a run that has not settled
    says so next to the outcome, so that "inverted" is not read as "turned over"."""
    top = tj.default_top()
    y0 = tj.initial_state(top, 0.1, 100.0)
    sol = tj.simulate(top, y0, 8.0, summary=True)
    text = repr(sol)
    assert text.startswith("Solution(model='full', result='successful'")
    assert f"t_invert={float(sol.t_invert):.6g} s" in text
    assert "outcome='inverted'" in text and "on its way" not in text
    # slow friction: at t1 the top is still rising
    slow = top.replace(mu=0.05)
    sol = tj.simulate(slow, tj.initial_state(slow, 0.1, 100.0), 8.0, summary=True)
    assert not bool(sol.settled)
    assert "(on its way: not settled by t_final)" in repr(sol)
    assert "theta_end=" in repr(sol)
    batch = jax.vmap(lambda s: tj.simulate(top, tj.initial_state(top, 0.1, s), 1.0, summary=True))(
        jnp.array([50.0, 60.0])
    )
    assert "f64[2" in repr(batch)
