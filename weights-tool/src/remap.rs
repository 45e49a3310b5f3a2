//! `--key-prefix OLD=NEW`: renaming key prefixes of checkpoints whose modules are named
//! differently from docs/SPEC.md section 6 (e.g. `obs_encoder.obs_nets.image.` for `obs_encoder.`).

use std::collections::BTreeMap;
use std::str::FromStr;

use crate::state_dict::StateDict;

/// One rule: keys starting with `old` have that prefix replaced by `new`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct KeyPrefix {
    pub old: String,
    pub new: String,
}

impl FromStr for KeyPrefix {
    type Err = String;

    fn from_str(rule: &str) -> Result<Self, Self::Err> {
        let (old, new) = rule
            .split_once('=')
            .ok_or_else(|| format!("expected OLD=NEW, found {rule:?}"))?;
        Ok(KeyPrefix {
            old: old.to_owned(),
            new: new.to_owned(),
        })
    }
}

impl KeyPrefix {
    fn apply(&self, key: &str) -> Option<String> {
        key.strip_prefix(self.old.as_str())
            .map(|rest| format!("{}{rest}", self.new))
    }
}

/// Two source keys renamed to the same key.
#[derive(Debug, PartialEq, Eq, thiserror::Error)]
#[error("--key-prefix renames both {first} and {second} to {renamed}")]
pub struct RemapCollision {
    pub first: String,
    pub second: String,
    pub renamed: String,
}

/// Renames every key (tensors and skipped entries) by the first rule whose prefix it has;
/// keys no rule matches stay as they are.
pub fn remap_keys(state_dict: StateDict, rules: &[KeyPrefix]) -> Result<StateDict, RemapCollision> {
    if rules.is_empty() {
        return Ok(state_dict);
    }
    let rename = |key: &str| {
        rules
            .iter()
            .find_map(|rule| rule.apply(key))
            .unwrap_or_else(|| key.to_owned())
    };
    Ok(StateDict {
        tensors: remap_map(state_dict.tensors, &rename)?,
        skipped: remap_map(state_dict.skipped, &rename)?,
        source: state_dict.source,
    })
}

fn remap_map<V>(
    map: BTreeMap<String, V>,
    rename: &impl Fn(&str) -> String,
) -> Result<BTreeMap<String, V>, RemapCollision> {
    let mut renamed_from: BTreeMap<String, String> = BTreeMap::new();
    let mut out = BTreeMap::new();
    for (key, value) in map {
        let renamed = rename(&key);
        if let Some(first) = renamed_from.insert(renamed.clone(), key.clone()) {
            return Err(RemapCollision {
                first,
                second: key,
                renamed,
            });
        }
        out.insert(renamed, value);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::state_dict::{Source, Tensor};

    fn state_dict(keys: &[&str]) -> StateDict {
        let mut state_dict = StateDict::new(Source::Safetensors);
        for key in keys {
            state_dict.insert(key.to_string(), Tensor::new(vec![1], vec![0.0]));
        }
        state_dict
    }

    #[test]
    fn parses_old_equals_new_and_allows_empty_sides() {
        assert_eq!(
            "a.=b.".parse::<KeyPrefix>().unwrap(),
            KeyPrefix {
                old: "a.".into(),
                new: "b.".into()
            }
        );
        assert_eq!(
            "module.=".parse::<KeyPrefix>().unwrap(),
            KeyPrefix {
                old: "module.".into(),
                new: String::new()
            }
        );
        assert!("no-equals".parse::<KeyPrefix>().is_err());
    }

    #[test]
    fn first_matching_rule_wins() {
        let rules = [
            "obs_encoder.obs_nets.image.=obs_encoder.".parse().unwrap(),
            "obs_encoder.=other.".parse().unwrap(),
        ];
        let remapped = remap_keys(
            state_dict(&[
                "obs_encoder.obs_nets.image.proj.0.bias",
                "model.x",
                "obs_encoder.y",
            ]),
            &rules,
        )
        .unwrap();
        let keys: Vec<_> = remapped.tensors.keys().cloned().collect();
        assert_eq!(keys, ["model.x", "obs_encoder.proj.0.bias", "other.y"]);
    }

    #[test]
    fn collisions_are_errors() {
        let rules = ["a.=".parse().unwrap()];
        let error = remap_keys(state_dict(&["a.x", "x"]), &rules).unwrap_err();
        assert_eq!(error.renamed, "x");
    }
}
