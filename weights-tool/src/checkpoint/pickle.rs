//! A pickle reader restricted to what `torch.save` writes: the opcodes Python 3's `Pickler`
//! emits for protocols 2 to 5 (torch.save uses 2 unless told otherwise), with persistent ids
//! for tensor storages. Nothing is executed: a call (`REDUCE`, `NEWOBJ`) becomes an
//! [`Object`] recording the callable and its arguments, so classes the tool has never seen
//! (OmegaConf configs, optimizers, dill-pickled workspace attributes) load as inert values.
//!
//! Why not a crate: serde-pickle has no persistent ids; candle-core's `pickle` module handles
//! torch archives but drags in candle's whole tensor stack (gemm, rayon, rand, tokenizers),
//! stops on opcodes such as `SHORT_BINUNICODE`, `MEMOIZE` and `POP_MARK`, and memoizes
//! snapshots, so a dict reached a second time through the memo reads back empty;
//! repugnant-pickle is an unmaintained 0.0.1 that handles flat state dicts only.
//!
//! Mutable containers live in an arena and values refer to them by index, so the memo shares
//! them as Python does and a dict filled after it was memoized is seen filled everywhere.

use std::collections::HashMap;
use std::fmt;

/// A pickled value. Containers and objects are [`Value::Node`]s into [`Pickle::nodes`].
#[derive(Clone, Debug, PartialEq)]
pub enum Value {
    None,
    Bool(bool),
    Int(i64),
    /// An integer wider than 64 bits; its value is never needed.
    BigInt,
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    /// A class or function named by module and qualified name (`GLOBAL`, `STACK_GLOBAL`).
    Global {
        module: String,
        name: String,
    },
    Node(usize),
}

/// A container or object.
#[derive(Clone, Debug, PartialEq)]
pub enum Node {
    Tuple(Vec<Value>),
    List(Vec<Value>),
    Dict(Vec<(Value, Value)>),
    /// `set` and `frozenset`.
    Set(Vec<Value>),
    Object(Object),
    /// What `persistent_load` would be called with (torch: a storage descriptor tuple).
    PersistentId(Value),
}

/// The result of calling `class` with `args` (`REDUCE`, `NEWOBJ`), never actually called.
#[derive(Clone, Debug, PartialEq)]
pub struct Object {
    pub class: Value,
    pub args: Value,
    /// The argument of `BUILD` (`__setstate__`), if any.
    pub state: Option<Value>,
    /// `SETITEMS` on the object: a dict subclass such as `OrderedDict`.
    pub items: Vec<(Value, Value)>,
    /// `APPENDS` on the object: a list subclass.
    pub list_items: Vec<Value>,
}

/// A whole unpickled value with the arena its containers live in.
#[derive(Debug)]
pub struct Pickle {
    pub nodes: Vec<Node>,
    pub root: Value,
}

/// Where and why unpickling stopped.
#[derive(Debug, PartialEq, Eq, thiserror::Error)]
#[error("pickle byte {offset}: {kind}")]
pub struct PickleError {
    pub offset: usize,
    pub kind: PickleErrorKind,
}

#[derive(Debug, PartialEq, Eq)]
pub enum PickleErrorKind {
    Truncated,
    UnknownOpcode(u8),
    /// An opcode that is valid pickle but that `torch.save` never writes.
    Unsupported(&'static str),
    UnsupportedProtocol(u8),
    StackUnderflow,
    NoMark,
    MissingMemo(u64),
    /// An opcode applied to a value it does not apply to (e.g. `SETITEMS` on a tuple).
    WrongType(&'static str),
    NoStop,
}

impl fmt::Display for PickleErrorKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Truncated => f.write_str("data ends inside an opcode (truncated pickle)"),
            Self::UnknownOpcode(op) => write!(f, "unknown opcode 0x{op:02x}"),
            Self::Unsupported(what) => write!(f, "unsupported opcode {what}"),
            Self::UnsupportedProtocol(version) => {
                write!(f, "pickle protocol {version} is newer than 5")
            }
            Self::StackUnderflow => f.write_str("stack underflow"),
            Self::NoMark => f.write_str("no mark on the stack"),
            Self::MissingMemo(id) => write!(f, "memo entry {id} was never stored"),
            Self::WrongType(what) => f.write_str(what),
            Self::NoStop => f.write_str("data ends without a STOP opcode"),
        }
    }
}

/// The class of `OrderedDict` and `defaultdict` instances, which behave as dicts here.
fn is_dict_class(class: &Value) -> bool {
    matches!(class, Value::Global { module, name }
        if module == "collections" && (name == "OrderedDict" || name == "defaultdict"))
}

impl Pickle {
    pub fn node(&self, value: &Value) -> Option<&Node> {
        match value {
            Value::Node(index) => self.nodes.get(*index),
            _ => None,
        }
    }

    /// The items of a dict or of a dict subclass instance (`OrderedDict`).
    pub fn dict_items(&self, value: &Value) -> Option<&[(Value, Value)]> {
        match self.node(value)? {
            Node::Dict(items) => Some(items),
            Node::Object(object) if is_dict_class(&object.class) => Some(&object.items),
            _ => None,
        }
    }

    /// The value stored under the string key `key` of a dict.
    pub fn dict_get(&self, value: &Value, key: &str) -> Option<&Value> {
        self.dict_items(value)?
            .iter()
            .find(|(k, _)| matches!(k, Value::Str(s) if s == key))
            .map(|(_, v)| v)
    }

    /// The string keys of a dict, for messages.
    pub fn dict_keys(&self, value: &Value) -> Vec<String> {
        self.dict_items(value)
            .unwrap_or_default()
            .iter()
            .map(|(key, _)| match key {
                Value::Str(key) => key.clone(),
                other => format!("{other:?}"),
            })
            .collect()
    }

    pub fn tuple(&self, value: &Value) -> Option<&[Value]> {
        match self.node(value)? {
            Node::Tuple(items) => Some(items),
            _ => None,
        }
    }

    /// A short description of a value's type, for messages.
    pub fn describe(&self, value: &Value) -> String {
        match value {
            Value::None => "None".into(),
            Value::Bool(_) => "bool".into(),
            Value::Int(_) | Value::BigInt => "int".into(),
            Value::Float(_) => "float".into(),
            Value::Str(_) => "str".into(),
            Value::Bytes(_) => "bytes".into(),
            Value::Global { module, name } => format!("{module}.{name}"),
            Value::Node(_) => match self.node(value) {
                Some(Node::Tuple(_)) => "tuple".into(),
                Some(Node::List(_)) => "list".into(),
                Some(Node::Dict(_)) => "dict".into(),
                Some(Node::Set(_)) => "set".into(),
                Some(Node::PersistentId(_)) => "persistent id".into(),
                Some(Node::Object(object)) => match &object.class {
                    Value::Global { module, name } => format!("{module}.{name} object"),
                    _ => "object".into(),
                },
                None => "dangling reference".into(),
            },
        }
    }
}

/// Unpickles `data` (a whole pickle, ending in `STOP`).
pub fn unpickle(data: &[u8]) -> Result<Pickle, PickleError> {
    let mut machine = Machine {
        input: Input { data, pos: 0 },
        stack: Vec::new(),
        marks: Vec::new(),
        memo: HashMap::new(),
        nodes: Vec::new(),
        op_start: 0,
    };
    let root = machine.run()?;
    Ok(Pickle {
        nodes: machine.nodes,
        root,
    })
}

struct Input<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Input<'a> {
    fn take(&mut self, len: usize) -> Option<&'a [u8]> {
        let end = self
            .pos
            .checked_add(len)
            .filter(|&end| end <= self.data.len())?;
        let bytes = &self.data[self.pos..end];
        self.pos = end;
        Some(bytes)
    }

    fn array<const N: usize>(&mut self) -> Option<[u8; N]> {
        self.take(N)
            .map(|bytes| bytes.try_into().expect("took N bytes"))
    }

    fn u8(&mut self) -> Option<u8> {
        self.array::<1>().map(|[byte]| byte)
    }

    /// A length prefix of `N` little-endian bytes.
    fn len<const N: usize>(&mut self) -> Option<usize> {
        let bytes = self.array::<N>()?;
        let mut wide = [0u8; 8];
        wide[..N].copy_from_slice(&bytes);
        usize::try_from(u64::from_le_bytes(wide)).ok()
    }

    /// A newline-terminated line (for `GLOBAL`).
    fn line(&mut self) -> Option<&'a [u8]> {
        let rest = &self.data[self.pos..];
        let end = rest.iter().position(|&byte| byte == b'\n')?;
        self.pos += end + 1;
        Some(&rest[..end])
    }
}

struct Machine<'a> {
    input: Input<'a>,
    stack: Vec<Value>,
    /// Stack heights at each `MARK`, innermost last (CPython's metastack).
    marks: Vec<usize>,
    memo: HashMap<u64, Value>,
    nodes: Vec<Node>,
    /// Offset of the opcode being executed, for errors.
    op_start: usize,
}

impl Machine<'_> {
    fn error(&self, kind: PickleErrorKind) -> PickleError {
        PickleError {
            offset: self.op_start,
            kind,
        }
    }

    fn truncated(&self) -> PickleError {
        self.error(PickleErrorKind::Truncated)
    }

    fn pop(&mut self) -> Result<Value, PickleError> {
        if self.marks.last() == Some(&self.stack.len()) {
            // Popping below the innermost mark would corrupt it.
            return Err(self.error(PickleErrorKind::StackUnderflow));
        }
        self.stack
            .pop()
            .ok_or_else(|| self.error(PickleErrorKind::StackUnderflow))
    }

    fn top(&self) -> Result<&Value, PickleError> {
        self.stack
            .last()
            .ok_or_else(|| self.error(PickleErrorKind::StackUnderflow))
    }

    fn pop_mark(&mut self) -> Result<Vec<Value>, PickleError> {
        let mark = self
            .marks
            .pop()
            .ok_or_else(|| self.error(PickleErrorKind::NoMark))?;
        Ok(self.stack.split_off(mark))
    }

    fn push_node(&mut self, node: Node) {
        self.nodes.push(node);
        self.stack.push(Value::Node(self.nodes.len() - 1));
    }

    fn node_mut(&mut self, value: &Value) -> Option<&mut Node> {
        match value {
            Value::Node(index) => self.nodes.get_mut(*index),
            _ => None,
        }
    }

    fn memo_get(&mut self, id: u64) -> Result<(), PickleError> {
        let value = self
            .memo
            .get(&id)
            .cloned()
            .ok_or_else(|| self.error(PickleErrorKind::MissingMemo(id)))?;
        self.stack.push(value);
        Ok(())
    }

    fn memo_put(&mut self, id: u64) -> Result<(), PickleError> {
        let value = self.top()?.clone();
        self.memo.insert(id, value);
        Ok(())
    }

    fn string(&mut self, len: Option<usize>) -> Result<Value, PickleError> {
        let bytes = len
            .and_then(|len| self.input.take(len))
            .ok_or_else(|| self.truncated())?;
        // Python writes str with "surrogatepass"; lone surrogates are not valid UTF-8 and
        // become U+FFFD, which can only matter for keys no model has.
        Ok(Value::Str(String::from_utf8_lossy(bytes).into_owned()))
    }

    fn bytes(&mut self, len: Option<usize>) -> Result<Value, PickleError> {
        let bytes = len
            .and_then(|len| self.input.take(len))
            .ok_or_else(|| self.truncated())?;
        Ok(Value::Bytes(bytes.to_vec()))
    }

    /// `LONG1` / `LONG4`: little-endian two's complement of `len` bytes.
    fn long(&mut self, len: Option<usize>) -> Result<Value, PickleError> {
        let bytes = len
            .and_then(|len| self.input.take(len))
            .ok_or_else(|| self.truncated())?;
        if bytes.len() > 8 {
            return Ok(Value::BigInt);
        }
        let negative = bytes.last().is_some_and(|&byte| byte & 0x80 != 0);
        let mut wide = if negative { [0xff; 8] } else { [0; 8] };
        wide[..bytes.len()].copy_from_slice(bytes);
        Ok(Value::Int(i64::from_le_bytes(wide)))
    }

    fn call(&mut self, class: Value, args: Value) {
        self.push_node(Node::Object(Object {
            class,
            args,
            state: None,
            items: Vec::new(),
            list_items: Vec::new(),
        }));
    }

    fn set_items(&mut self, pairs: Vec<Value>) -> Result<(), PickleError> {
        let target = self.top()?.clone();
        let mut pairs = pairs.into_iter();
        let mut items = Vec::new();
        while let (Some(key), Some(value)) = (pairs.next(), pairs.next()) {
            items.push((key, value));
        }
        match self.node_mut(&target) {
            Some(Node::Dict(dict)) => dict.extend(items),
            Some(Node::Object(object)) => object.items.extend(items),
            _ => return Err(self.error(PickleErrorKind::WrongType("SETITEMS on a non-dict"))),
        }
        Ok(())
    }

    fn append(&mut self, values: Vec<Value>) -> Result<(), PickleError> {
        let target = self.top()?.clone();
        match self.node_mut(&target) {
            Some(Node::List(list)) => list.extend(values),
            Some(Node::Object(object)) => object.list_items.extend(values),
            _ => return Err(self.error(PickleErrorKind::WrongType("APPENDS on a non-list"))),
        }
        Ok(())
    }

    fn build(&mut self) -> Result<(), PickleError> {
        let state = self.pop()?;
        let target = self.top()?.clone();
        // State on anything but an object (e.g. attributes of a dict) is not needed.
        if let Some(Node::Object(object)) = self.node_mut(&target) {
            object.state = Some(state);
        }
        Ok(())
    }

    fn run(&mut self) -> Result<Value, PickleError> {
        loop {
            self.op_start = self.input.pos;
            let Some(op) = self.input.u8() else {
                return Err(self.error(PickleErrorKind::NoStop));
            };
            if op == STOP {
                return self.pop();
            }
            self.step(op)?;
        }
    }

    fn step(&mut self, op: u8) -> Result<(), PickleError> {
        let unsupported = |what| Err(self.error(PickleErrorKind::Unsupported(what)));
        match op {
            PROTO => {
                let version = self.input.u8().ok_or_else(|| self.truncated())?;
                if version > 5 {
                    return Err(self.error(PickleErrorKind::UnsupportedProtocol(version)));
                }
            }
            FRAME => {
                // Framing only batches reads; the whole pickle is in memory already.
                self.input.len::<8>().ok_or_else(|| self.truncated())?;
            }
            MARK => self.marks.push(self.stack.len()),
            POP => {
                if self.marks.last() == Some(&self.stack.len()) {
                    self.marks.pop();
                } else {
                    self.pop()?;
                }
            }
            POP_MARK => {
                self.pop_mark()?;
            }
            DUP => {
                let top = self.top()?.clone();
                self.stack.push(top);
            }
            NONE => self.stack.push(Value::None),
            NEWTRUE => self.stack.push(Value::Bool(true)),
            NEWFALSE => self.stack.push(Value::Bool(false)),
            BININT => {
                let value = self.input.array::<4>().ok_or_else(|| self.truncated())?;
                self.stack
                    .push(Value::Int(i32::from_le_bytes(value).into()));
            }
            BININT1 => {
                let value = self.input.u8().ok_or_else(|| self.truncated())?;
                self.stack.push(Value::Int(value.into()));
            }
            BININT2 => {
                let value = self.input.array::<2>().ok_or_else(|| self.truncated())?;
                self.stack
                    .push(Value::Int(u16::from_le_bytes(value).into()));
            }
            LONG1 => {
                let len = self.input.len::<1>();
                let value = self.long(len)?;
                self.stack.push(value);
            }
            LONG4 => {
                let len = self.input.len::<4>();
                let value = self.long(len)?;
                self.stack.push(value);
            }
            BINFLOAT => {
                // The one big-endian field of the format.
                let value = self.input.array::<8>().ok_or_else(|| self.truncated())?;
                self.stack.push(Value::Float(f64::from_be_bytes(value)));
            }
            SHORT_BINUNICODE => {
                let len = self.input.len::<1>();
                let value = self.string(len)?;
                self.stack.push(value);
            }
            BINUNICODE => {
                let len = self.input.len::<4>();
                let value = self.string(len)?;
                self.stack.push(value);
            }
            BINUNICODE8 => {
                let len = self.input.len::<8>();
                let value = self.string(len)?;
                self.stack.push(value);
            }
            SHORT_BINBYTES => {
                let len = self.input.len::<1>();
                let value = self.bytes(len)?;
                self.stack.push(value);
            }
            BINBYTES => {
                let len = self.input.len::<4>();
                let value = self.bytes(len)?;
                self.stack.push(value);
            }
            BINBYTES8 | BYTEARRAY8 => {
                let len = self.input.len::<8>();
                let value = self.bytes(len)?;
                self.stack.push(value);
            }
            EMPTY_TUPLE => self.push_node(Node::Tuple(Vec::new())),
            TUPLE => {
                let items = self.pop_mark()?;
                self.push_node(Node::Tuple(items));
            }
            TUPLE1 | TUPLE2 | TUPLE3 => {
                let len = usize::from(op - TUPLE1 + 1);
                if self.stack.len() < len + self.marks.last().copied().unwrap_or(0) {
                    return Err(self.error(PickleErrorKind::StackUnderflow));
                }
                let items = self.stack.split_off(self.stack.len() - len);
                self.push_node(Node::Tuple(items));
            }
            EMPTY_LIST => self.push_node(Node::List(Vec::new())),
            APPEND => {
                let value = self.pop()?;
                self.append(vec![value])?;
            }
            APPENDS => {
                let values = self.pop_mark()?;
                self.append(values)?;
            }
            EMPTY_DICT => self.push_node(Node::Dict(Vec::new())),
            SETITEM => {
                let value = self.pop()?;
                let key = self.pop()?;
                self.set_items(vec![key, value])?;
            }
            SETITEMS => {
                let pairs = self.pop_mark()?;
                self.set_items(pairs)?;
            }
            EMPTY_SET => self.push_node(Node::Set(Vec::new())),
            ADDITEMS => {
                let values = self.pop_mark()?;
                let target = self.top()?.clone();
                match self.node_mut(&target) {
                    Some(Node::Set(set)) => set.extend(values),
                    _ => {
                        return Err(self.error(PickleErrorKind::WrongType("ADDITEMS on a non-set")));
                    }
                }
            }
            FROZENSET => {
                let values = self.pop_mark()?;
                self.push_node(Node::Set(values));
            }
            GLOBAL => {
                let module = self.input.line().ok_or_else(|| self.truncated())?;
                let name = self.input.line().ok_or_else(|| self.truncated())?;
                self.stack.push(Value::Global {
                    module: String::from_utf8_lossy(module).into_owned(),
                    name: String::from_utf8_lossy(name).into_owned(),
                });
            }
            STACK_GLOBAL => {
                let name = self.pop()?;
                let module = self.pop()?;
                let (Value::Str(module), Value::Str(name)) = (module, name) else {
                    return Err(
                        self.error(PickleErrorKind::WrongType("STACK_GLOBAL needs two strings"))
                    );
                };
                self.stack.push(Value::Global { module, name });
            }
            REDUCE | NEWOBJ => {
                let args = self.pop()?;
                let class = self.pop()?;
                self.call(class, args);
            }
            NEWOBJ_EX => {
                // Keyword arguments only configure the instance; they are not needed.
                let _kwargs = self.pop()?;
                let args = self.pop()?;
                let class = self.pop()?;
                self.call(class, args);
            }
            BUILD => self.build()?,
            BINPERSID => {
                let id = self.pop()?;
                self.push_node(Node::PersistentId(id));
            }
            BINPUT => {
                let id = self.input.len::<1>().ok_or_else(|| self.truncated())?;
                self.memo_put(id as u64)?;
            }
            LONG_BINPUT => {
                let id = self.input.len::<4>().ok_or_else(|| self.truncated())?;
                self.memo_put(id as u64)?;
            }
            MEMOIZE => {
                let id = self.memo.len() as u64;
                self.memo_put(id)?;
            }
            BINGET => {
                let id = self.input.len::<1>().ok_or_else(|| self.truncated())?;
                self.memo_get(id as u64)?;
            }
            LONG_BINGET => {
                let id = self.input.len::<4>().ok_or_else(|| self.truncated())?;
                self.memo_get(id as u64)?;
            }
            EXT1 | EXT2 | EXT4 => return unsupported("EXT (copyreg extension registry)"),
            NEXT_BUFFER | READONLY_BUFFER => return unsupported("NEXT_BUFFER (out-of-band data)"),
            INT | LONG | FLOAT | STRING | BINSTRING | SHORT_BINSTRING | UNICODE | LIST | DICT
            | INST | OBJ | PUT | GET | PERSID => {
                return unsupported(
                    "of text protocol 0/1 or Python 2 (torch.save writes 2 or newer)",
                );
            }
            other => return Err(self.error(PickleErrorKind::UnknownOpcode(other))),
        }
        Ok(())
    }
}

// Opcodes, named as in CPython's Lib/pickle.py.
const MARK: u8 = b'(';
const STOP: u8 = b'.';
const POP: u8 = b'0';
const POP_MARK: u8 = b'1';
const DUP: u8 = b'2';
const FLOAT: u8 = b'F';
const INT: u8 = b'I';
const BININT: u8 = b'J';
const BININT1: u8 = b'K';
const LONG: u8 = b'L';
const BININT2: u8 = b'M';
const NONE: u8 = b'N';
const PERSID: u8 = b'P';
const BINPERSID: u8 = b'Q';
const REDUCE: u8 = b'R';
const STRING: u8 = b'S';
const BINSTRING: u8 = b'T';
const SHORT_BINSTRING: u8 = b'U';
const UNICODE: u8 = b'V';
const BINUNICODE: u8 = b'X';
const APPEND: u8 = b'a';
const BUILD: u8 = b'b';
const GLOBAL: u8 = b'c';
const DICT: u8 = b'd';
const EMPTY_DICT: u8 = b'}';
const APPENDS: u8 = b'e';
const GET: u8 = b'g';
const BINGET: u8 = b'h';
const INST: u8 = b'i';
const LONG_BINGET: u8 = b'j';
const LIST: u8 = b'l';
const EMPTY_LIST: u8 = b']';
const OBJ: u8 = b'o';
const PUT: u8 = b'p';
const BINPUT: u8 = b'q';
const LONG_BINPUT: u8 = b'r';
const SETITEM: u8 = b's';
const TUPLE: u8 = b't';
const EMPTY_TUPLE: u8 = b')';
const SETITEMS: u8 = b'u';
const BINFLOAT: u8 = b'G';
const PROTO: u8 = 0x80;
const NEWOBJ: u8 = 0x81;
const EXT1: u8 = 0x82;
const EXT2: u8 = 0x83;
const EXT4: u8 = 0x84;
const TUPLE1: u8 = 0x85;
const TUPLE2: u8 = 0x86;
const TUPLE3: u8 = 0x87;
const NEWTRUE: u8 = 0x88;
const NEWFALSE: u8 = 0x89;
const LONG1: u8 = 0x8a;
const LONG4: u8 = 0x8b;
const BINBYTES: u8 = b'B';
const SHORT_BINBYTES: u8 = b'C';
const SHORT_BINUNICODE: u8 = 0x8c;
const BINUNICODE8: u8 = 0x8d;
const BINBYTES8: u8 = 0x8e;
const EMPTY_SET: u8 = 0x8f;
const ADDITEMS: u8 = 0x90;
const FROZENSET: u8 = 0x91;
const NEWOBJ_EX: u8 = 0x92;
const STACK_GLOBAL: u8 = 0x93;
const MEMOIZE: u8 = 0x94;
const FRAME: u8 = 0x95;
const BYTEARRAY8: u8 = 0x96;
const NEXT_BUFFER: u8 = 0x97;
const READONLY_BUFFER: u8 = 0x98;

#[cfg(test)]
mod tests {
    use super::*;

    // Made with CPython 3.11: pickle.dumps(x, protocol=2) (or as stated).

    #[test]
    fn dict_of_ints_strings_and_floats() {
        // {'a': 1, 'b': -2, 'c': 1.5, 'd': 'x', 'e': 2**40, 'f': None, 'g': True}
        let data = b"\x80\x02}q\x00(X\x01\x00\x00\x00aq\x01K\x01X\x01\x00\x00\x00bq\x02J\xfe\xff\xff\xffX\x01\x00\x00\x00cq\x03G?\xf8\x00\x00\x00\x00\x00\x00X\x01\x00\x00\x00dq\x04X\x01\x00\x00\x00xq\x05X\x01\x00\x00\x00eq\x06\x8a\x06\x00\x00\x00\x00\x00\x01X\x01\x00\x00\x00fq\x07NX\x01\x00\x00\x00gq\x08\x88u.";
        let pickle = unpickle(data).unwrap();
        let get = |key| pickle.dict_get(&pickle.root, key).unwrap().clone();
        assert_eq!(get("a"), Value::Int(1));
        assert_eq!(get("b"), Value::Int(-2));
        assert_eq!(get("c"), Value::Float(1.5));
        assert_eq!(get("d"), Value::Str("x".into()));
        assert_eq!(get("e"), Value::Int(1 << 40));
        assert_eq!(get("f"), Value::None);
        assert_eq!(get("g"), Value::Bool(true));
    }

    #[test]
    fn memo_shares_containers_filled_after_memoizing() {
        // d = {}; d['k'] = 1; pickle.dumps({'x': d, 'y': d}, protocol=2):
        // the second reference is a BINGET of the dict memoized before its items.
        let data = b"\x80\x02}q\x00(X\x01\x00\x00\x00xq\x01}q\x02X\x01\x00\x00\x00kq\x03K\x01sX\x01\x00\x00\x00yq\x04h\x02u.";
        let pickle = unpickle(data).unwrap();
        let y = pickle.dict_get(&pickle.root, "y").unwrap();
        assert_eq!(pickle.dict_get(y, "k"), Some(&Value::Int(1)));
    }

    #[test]
    fn protocol_4_framing_memoize_and_stack_global() {
        // pickle.dumps(collections.OrderedDict(a=1), protocol=4)
        let data = b"\x80\x04\x95)\x00\x00\x00\x00\x00\x00\x00\x8c\x0bcollections\x94\x8c\x0bOrderedDict\x94\x93\x94)R\x94\x8c\x01a\x94K\x01s.";
        let pickle = unpickle(data).unwrap();
        assert_eq!(pickle.dict_get(&pickle.root, "a"), Some(&Value::Int(1)));
        assert_eq!(
            pickle.describe(&pickle.root),
            "collections.OrderedDict object"
        );
    }

    #[test]
    fn unknown_classes_load_as_inert_objects() {
        // class Foo: pass; f = Foo(); f.x = {1}; pickle.dumps(f, protocol=2)
        let data = b"\x80\x02c__main__\nFoo\nq\x00)\x81q\x01}q\x02X\x01\x00\x00\x00xq\x03c__builtin__\nset\nq\x04]q\x05K\x01a\x85q\x06Rq\x07sb.";
        let pickle = unpickle(data).unwrap();
        assert_eq!(pickle.describe(&pickle.root), "__main__.Foo object");
        let Some(Node::Object(object)) = pickle.node(&pickle.root) else {
            panic!("not an object")
        };
        let state = object.state.as_ref().unwrap();
        assert_eq!(
            pickle.describe(pickle.dict_get(state, "x").unwrap()),
            "__builtin__.set object"
        );
    }

    #[test]
    fn persistent_ids_are_kept() {
        // A Pickler whose persistent_id returns ('storage', 'k') for the string 'T'.
        let data =
            b"\x80\x02]q\x00X\x07\x00\x00\x00storageq\x01X\x01\x00\x00\x00kq\x02\x86q\x03Qa.";
        let pickle = unpickle(data).unwrap();
        let Some(Node::List(items)) = pickle.node(&pickle.root) else {
            panic!("not a list")
        };
        let Some(Node::PersistentId(id)) = pickle.node(&items[0]) else {
            panic!("not a persistent id")
        };
        assert_eq!(
            pickle.tuple(id).unwrap(),
            [Value::Str("storage".into()), Value::Str("k".into())]
        );
    }

    #[test]
    fn truncation_and_garbage_are_errors_with_offsets() {
        let data = b"\x80\x02}q\x00(X\x01\x00\x00\x00aq\x01K\x01u.";
        for len in 0..data.len() {
            assert!(
                unpickle(&data[..len]).is_err(),
                "prefix of {len} bytes accepted"
            );
        }
        let error = unpickle(b"\x80\x02\xff.").unwrap_err();
        assert_eq!(
            error,
            PickleError {
                offset: 2,
                kind: PickleErrorKind::UnknownOpcode(0xff)
            }
        );
        assert_eq!(error.to_string(), "pickle byte 2: unknown opcode 0xff");
        assert!(unpickle(b"\x80\x02X\xff\xff\xff\x7f.").is_err());
        assert!(unpickle(b"\x80\x02u.").is_err());
    }
}
