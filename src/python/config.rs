//! Config bindings: the Rust [`DecodConfig`] is the single source of defaults; Python gets it
//! as TOML (to print) or JSON (to read).

use pyo3::prelude::*;

use crate::config::{DecodConfig, Preset};

use super::errors::to_py_err;

/// Every parameter of `preset` as TOML.
#[pyfunction]
fn default_config_toml(preset: &str) -> PyResult<String> {
    let preset: Preset = preset.parse().map_err(to_py_err)?;
    DecodConfig::preset(preset)
        .to_toml_string()
        .map_err(to_py_err)
}

/// `preset` overridden by the TOML text `overrides`, validated, as JSON.
#[pyfunction]
#[pyo3(signature = (preset, overrides = ""))]
fn resolve_config_json(preset: &str, overrides: &str) -> PyResult<String> {
    let preset: Preset = preset.parse().map_err(to_py_err)?;
    let config = DecodConfig::from_toml_str(overrides, preset).map_err(to_py_err)?;
    serde_json::to_string(&config)
        .map_err(|e| to_py_err(crate::DecodError::config("<config>", e.to_string())))
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(default_config_toml, m)?)?;
    m.add_function(wrap_pyfunction!(resolve_config_json, m)?)?;
    Ok(())
}
