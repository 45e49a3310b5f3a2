//! The engine's top-level modules form layers: no module reaches, through `crate::` paths,
//! back to itself. Configuration, errors, shapes and the file format sit at the bottom, the
//! kernels on their own contract and plain shapes, the model stages above them and the
//! policy on top; a cycle would mean a change in one layer can break the one below it.
//!
//! The check reads the sources (comments stripped), so it sees every `use crate::...` and
//! every path written in place (`crate::plan::ArenaPlan::new(...)`), in any file of a
//! module's tree.

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};

type Graph = BTreeMap<String, BTreeSet<String>>;

/// `text` without `//` comments (line and doc comments) or `/* */` blocks. String literals are
/// not parsed: the engine's contain no `//` before a `crate::` path.
fn strip_comments(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while !rest.is_empty() {
        if let Some(after) = rest.strip_prefix("/*") {
            rest = after.find("*/").map_or("", |end| &after[end + 2..]);
        } else if rest.starts_with("//") {
            rest = rest.find('\n').map_or("", |end| &rest[end..]);
        } else {
            let next = rest.chars().next().unwrap();
            out.push(next);
            rest = &rest[next.len_utf8()..];
        }
    }
    out
}

fn identifier(text: &str) -> &str {
    let end = text
        .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .unwrap_or(text.len());
    &text[..end]
}

/// The top-level modules `code` names through `crate::`: `crate::a::...`, and each item's
/// first segment in `crate::{a, b::c, d::{e, f}}`.
fn crate_references(code: &str) -> BTreeSet<String> {
    let mut found = BTreeSet::new();
    for (start, _) in code.match_indices("crate::") {
        // `scdp_crate::` or similar is not this crate.
        if code[..start]
            .chars()
            .next_back()
            .is_some_and(|c| c.is_ascii_alphanumeric() || c == '_')
        {
            continue;
        }
        let rest = code[start + "crate::".len()..].trim_start();
        if let Some(group) = rest.strip_prefix('{') {
            let mut depth = 0;
            let mut item_start = true;
            for (offset, c) in group.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => break,
                    '}' => depth -= 1,
                    ',' if depth == 0 => item_start = true,
                    c if c.is_whitespace() => {}
                    _ if item_start && depth == 0 => {
                        let name = identifier(&group[offset..]);
                        if !name.is_empty() {
                            found.insert(name.to_string());
                        }
                        item_start = false;
                    }
                    _ => {}
                }
            }
        } else {
            let name = identifier(rest);
            if !name.is_empty() {
                found.insert(name.to_string());
            }
        }
    }
    found
}

/// The modules `lib.rs` declares (`mod name;` or `pub mod name;`).
fn top_level_modules(lib: &str) -> Vec<String> {
    strip_comments(lib)
        .lines()
        .filter_map(|line| {
            let line = line.trim();
            let line = line.strip_prefix("pub ").unwrap_or(line);
            let name = line.strip_prefix("mod ")?.strip_suffix(';')?;
            Some(name.trim().to_string())
        })
        .collect()
}

fn rust_files(directory: &Path, files: &mut Vec<PathBuf>) {
    for entry in fs::read_dir(directory).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, files);
        } else if path.extension().is_some_and(|extension| extension == "rs") {
            files.push(path);
        }
    }
}

/// Each top-level module of the crate at `source` and the other top-level modules it names.
fn module_graph(source: &Path) -> Graph {
    let lib = fs::read_to_string(source.join("lib.rs")).unwrap();
    let modules = top_level_modules(&lib);
    assert!(!modules.is_empty(), "no modules found in lib.rs");
    let mut graph = Graph::new();
    for module in &modules {
        let mut files = Vec::new();
        let file = source.join(format!("{module}.rs"));
        if file.exists() {
            files.push(file);
        }
        let directory = source.join(module);
        if directory.is_dir() {
            rust_files(&directory, &mut files);
        }
        assert!(!files.is_empty(), "no source for module {module}");
        let mut uses = BTreeSet::new();
        for file in files {
            let code = strip_comments(&fs::read_to_string(&file).unwrap());
            uses.extend(crate_references(&code));
        }
        uses.remove(module);
        uses.retain(|name| modules.contains(name));
        graph.insert(module.clone(), uses);
    }
    graph
}

/// A cycle of `graph` as the path `a -> b -> ... -> a`, if there is one.
fn find_cycle(graph: &Graph) -> Option<Vec<String>> {
    #[derive(Clone, Copy, PartialEq)]
    enum Mark {
        Unvisited,
        OnPath,
        Done,
    }
    fn visit(
        node: &str,
        graph: &Graph,
        marks: &mut BTreeMap<String, Mark>,
        path: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        marks.insert(node.to_string(), Mark::OnPath);
        path.push(node.to_string());
        for next in graph.get(node).into_iter().flatten() {
            match marks.get(next.as_str()).copied().unwrap_or(Mark::Unvisited) {
                Mark::OnPath => {
                    let start = path.iter().position(|name| name == next).unwrap();
                    let mut cycle = path[start..].to_vec();
                    cycle.push(next.clone());
                    return Some(cycle);
                }
                Mark::Unvisited => {
                    if let Some(cycle) = visit(next, graph, marks, path) {
                        return Some(cycle);
                    }
                }
                Mark::Done => {}
            }
        }
        path.pop();
        marks.insert(node.to_string(), Mark::Done);
        None
    }
    let mut marks = BTreeMap::new();
    for node in graph.keys() {
        if marks.get(node.as_str()).copied().unwrap_or(Mark::Unvisited) == Mark::Unvisited
            && let Some(cycle) = visit(node, graph, &mut marks, &mut Vec::new())
        {
            return Some(cycle);
        }
    }
    None
}

/// The modules in layers: each layer's modules name only modules of the layers below.
fn layers(graph: &Graph) -> Vec<Vec<String>> {
    let mut placed = BTreeSet::new();
    let mut layers = Vec::new();
    while placed.len() < graph.len() {
        let layer: Vec<String> = graph
            .iter()
            .filter(|(name, uses)| !placed.contains(*name) && uses.is_subset(&placed))
            .map(|(name, _)| name.clone())
            .collect();
        assert!(!layer.is_empty(), "layers of a graph with a cycle");
        placed.extend(layer.iter().cloned());
        layers.push(layer);
    }
    layers
}

#[test]
fn engine_modules_form_no_cycle() {
    let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let graph = module_graph(&source);
    if let Some(cycle) = find_cycle(&graph) {
        let edges: Vec<String> = graph
            .iter()
            .map(|(name, uses)| format!("  {name} -> {uses:?}"))
            .collect();
        panic!(
            "engine/src's top-level modules form a cycle: {}\nall references:\n{}",
            cycle.join(" -> "),
            edges.join("\n")
        );
    }
    for (depth, layer) in layers(&graph).iter().enumerate() {
        println!("layer {depth}: {}", layer.join(", "));
    }
}

#[test]
fn the_kernels_know_neither_the_model_nor_its_weights() {
    let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let graph = module_graph(&source);
    let kernels = &graph["kernels"];
    let allowed: BTreeSet<String> = ["shape".to_string()].into();
    assert!(
        kernels.is_subset(&allowed),
        "kernels names {:?}; it may name only its own contract and the plain shapes",
        kernels.difference(&allowed).collect::<Vec<_>>()
    );
}

#[test]
fn the_checker_reads_every_form_of_path_and_finds_a_planted_cycle() {
    let code = strip_comments(
        "use crate::a::X;\n// crate::commented\nuse crate::{b, c::{D, E}, d::F};\n\
         fn f() { crate::e::g(); my_crate::h(); }\n/* crate::blocked */",
    );
    let found: Vec<String> = crate_references(&code).into_iter().collect();
    assert_eq!(found, ["a", "b", "c", "d", "e"]);

    let lib = "//! crate docs\npub mod a;\nmod b;\n#[cfg(test)]\nmod tests {}\n";
    assert_eq!(top_level_modules(lib), ["a", "b"]);

    let edge = |from: &str, to: &[&str]| {
        (
            from.to_string(),
            to.iter().map(|name| name.to_string()).collect(),
        )
    };
    let acyclic: Graph = [edge("a", &["b"]), edge("b", &["c"]), edge("c", &[])].into();
    assert_eq!(find_cycle(&acyclic), None);
    assert_eq!(layers(&acyclic), [["c"], ["b"], ["a"]]);
    let cyclic: Graph = [edge("a", &["b"]), edge("b", &["c"]), edge("c", &["a"])].into();
    let cycle = find_cycle(&cyclic).expect("the planted cycle");
    assert_eq!(cycle.first(), cycle.last());
    assert_eq!(cycle.len(), 4);
}
