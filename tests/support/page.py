"""The web page driven as a person uses it, through selenium (tests/page, bench/bench_real.py):
waits that report what the page said when they time out, form fields, file inputs, and a
ranking over generated candidates."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

from selenium.common.exceptions import TimeoutException
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait


def wait(driver, condition: Callable[[Any], Any], timeout: float = 40.0, what: str = "the page") -> Any:
    """What `condition` returns once it is truthy; past `timeout` seconds an AssertionError that
    quotes the page's message lines (where it says what went wrong)."""
    try:
        return WebDriverWait(driver, timeout, poll_frequency=0.1).until(condition)
    except TimeoutException:
        said = driver.execute_script("return [...document.querySelectorAll('.message')].filter(p => p.textContent)"
                                     ".map(p => p.id + ': ' + p.textContent)")
        raise AssertionError(f"timed out waiting for {what}; the page says: {said!r}") from None


def text_of(driver, element_id: str) -> str:
    return driver.find_element(By.ID, element_id).text


def set_field(driver, element_id: str, value: Any) -> None:
    field = driver.find_element(By.ID, element_id)
    field.clear()
    field.send_keys(str(value))


def choose_files(driver, element_id: str, *paths: Path) -> None:
    """Pick `paths` in a file input, as one choice (a fresh `change` event even for the same files)."""
    driver.execute_script("document.getElementById(arguments[0]).value = ''", element_id)
    driver.find_element(By.ID, element_id).send_keys("\n".join(str(p) for p in paths))


def console_errors(driver, expected: tuple[str, ...] = ()) -> list[str]:
    """The browser's error messages since the last call, but for failed requests made on
    purpose (`expected`: parts of their messages, e.g. a status code)."""
    return [entry["message"] for entry in driver.get_log("browser") if entry["level"] == "SEVERE"
            and not any(part in entry["message"] for part in expected)]


def grid_loaded(job: str, cards: int) -> Callable[[Any], bool]:
    """A wait condition: the `job` ("rank" or "select") grid shows `cards` cards, every image loaded."""
    return lambda d: (len(d.find_elements(By.CSS_SELECTOR, f"#{job}-grid li.card")) == cards and d.execute_script(
        f"return [...document.querySelectorAll('#{job}-grid img')].every(i => i.complete && i.naturalWidth > 0)"))


def run_on_candidates(driver, count: int, job: str, fields: dict[str, Any], cards: int | None = None,
                      timeout: float = 40.0) -> None:
    """Ask for `count` generated candidates, fill `fields`, press the job's button ("rank" or
    "select") and wait until its grid shows `cards` (default `count`) cards with every image loaded."""
    set_field(driver, "gen-count", count)
    driver.find_element(By.ID, "gen-elevation").click()          # the change event takes the new count
    for field, value in fields.items():
        set_field(driver, field, value)
    wait(driver, lambda d: (d.execute_script("return state.spec") or {}).get("count") == count,
         what=f"a spec of {count} candidates")
    driver.find_element(By.ID, f"{job}-run").click()
    wait(driver, grid_loaded(job, count if cards is None else cards), timeout, what=f"the {job} grid and its images")
