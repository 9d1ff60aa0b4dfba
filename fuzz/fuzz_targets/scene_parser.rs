//! Fuzz target: the scene readers must never panic. Any byte string is read
//! as TOML and as JSON; a scene that parses is validated, and a valid one is
//! turned into a model (free-dof numbering, element geometry, loads).
#![no_main]

use libfuzzer_sys::fuzz_target;
use nsdd::model::Model;
use nsdd::scene::Scene;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    for parsed in [Scene::from_toml_str(text), Scene::from_json_str(text)] {
        if let Ok(scene) = parsed {
            if scene.validate().is_ok() {
                let _ = Model::from_scene(&scene);
            }
            // Writing back never fails on a scene that was read.
            let _ = scene.to_json_string();
        }
    }
});
