//! The wire shape of a serde value: a serializer that records struct names, field names and
//! primitive types in order, instead of bytes. CDR encodes exactly these in this order, so two
//! equal shapes mean two identical wire layouts.
#![allow(dead_code)]

use serde::ser::{self, Serialize};
use std::fmt;

/// The shape of one value.
#[derive(Debug, Clone, PartialEq)]
pub enum Shape {
    /// `bool`.
    Bool,
    /// `int8`.
    I8,
    /// `int16`.
    I16,
    /// `int32`.
    I32,
    /// `int64`.
    I64,
    /// `uint8` / `byte`.
    U8,
    /// `uint16`.
    U16,
    /// `uint32`.
    U32,
    /// `uint64`.
    U64,
    /// `float32`.
    F32,
    /// `float64`.
    F64,
    /// `string`.
    Str,
    /// An unbounded sequence; the element shape is that of the first element (sample values
    /// must have one).
    Seq(Option<Box<Shape>>),
    /// A struct: its fields in order.
    Struct(Vec<(String, Shape)>),
}

/// A shape error (unsupported serde construct).
#[derive(Debug)]
pub struct ShapeError(String);

impl fmt::Display for ShapeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}
impl std::error::Error for ShapeError {}
impl ser::Error for ShapeError {
    fn custom<T: fmt::Display>(msg: T) -> Self {
        ShapeError(msg.to_string())
    }
}

/// The shape of `v`.
pub fn shape_of<T: Serialize>(v: &T) -> Shape {
    v.serialize(Recorder).expect("shape of a message value")
}

struct Recorder;

fn unsupported<T>(what: &str) -> Result<T, ShapeError> {
    Err(ShapeError(format!("{what} does not occur in ROS messages")))
}

/// Collects the elements of a sequence.
pub struct SeqRec(Vec<Shape>);
/// Collects the fields of a struct.
pub struct StructRec(Vec<(String, Shape)>);

impl ser::Serializer for Recorder {
    type Ok = Shape;
    type Error = ShapeError;
    type SerializeSeq = SeqRec;
    type SerializeTuple = ser::Impossible<Shape, ShapeError>;
    type SerializeTupleStruct = ser::Impossible<Shape, ShapeError>;
    type SerializeTupleVariant = ser::Impossible<Shape, ShapeError>;
    type SerializeMap = ser::Impossible<Shape, ShapeError>;
    type SerializeStruct = StructRec;
    type SerializeStructVariant = ser::Impossible<Shape, ShapeError>;

    fn serialize_bool(self, _: bool) -> Result<Shape, ShapeError> {
        Ok(Shape::Bool)
    }
    fn serialize_i8(self, _: i8) -> Result<Shape, ShapeError> {
        Ok(Shape::I8)
    }
    fn serialize_i16(self, _: i16) -> Result<Shape, ShapeError> {
        Ok(Shape::I16)
    }
    fn serialize_i32(self, _: i32) -> Result<Shape, ShapeError> {
        Ok(Shape::I32)
    }
    fn serialize_i64(self, _: i64) -> Result<Shape, ShapeError> {
        Ok(Shape::I64)
    }
    fn serialize_u8(self, _: u8) -> Result<Shape, ShapeError> {
        Ok(Shape::U8)
    }
    fn serialize_u16(self, _: u16) -> Result<Shape, ShapeError> {
        Ok(Shape::U16)
    }
    fn serialize_u32(self, _: u32) -> Result<Shape, ShapeError> {
        Ok(Shape::U32)
    }
    fn serialize_u64(self, _: u64) -> Result<Shape, ShapeError> {
        Ok(Shape::U64)
    }
    fn serialize_f32(self, _: f32) -> Result<Shape, ShapeError> {
        Ok(Shape::F32)
    }
    fn serialize_f64(self, _: f64) -> Result<Shape, ShapeError> {
        Ok(Shape::F64)
    }
    fn serialize_char(self, _: char) -> Result<Shape, ShapeError> {
        unsupported("char")
    }
    fn serialize_str(self, _: &str) -> Result<Shape, ShapeError> {
        Ok(Shape::Str)
    }
    fn serialize_bytes(self, _: &[u8]) -> Result<Shape, ShapeError> {
        Ok(Shape::Seq(Some(Box::new(Shape::U8))))
    }
    fn serialize_none(self) -> Result<Shape, ShapeError> {
        unsupported("Option")
    }
    fn serialize_some<T: ?Sized + Serialize>(self, _: &T) -> Result<Shape, ShapeError> {
        unsupported("Option")
    }
    fn serialize_unit(self) -> Result<Shape, ShapeError> {
        unsupported("()")
    }
    fn serialize_unit_struct(self, _: &'static str) -> Result<Shape, ShapeError> {
        unsupported("a unit struct")
    }
    fn serialize_unit_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
    ) -> Result<Shape, ShapeError> {
        unsupported("an enum")
    }
    fn serialize_newtype_struct<T: ?Sized + Serialize>(
        self,
        _: &'static str,
        v: &T,
    ) -> Result<Shape, ShapeError> {
        v.serialize(self)
    }
    fn serialize_newtype_variant<T: ?Sized + Serialize>(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: &T,
    ) -> Result<Shape, ShapeError> {
        unsupported("an enum")
    }
    fn serialize_seq(self, _: Option<usize>) -> Result<SeqRec, ShapeError> {
        Ok(SeqRec(Vec::new()))
    }
    fn serialize_tuple(self, _: usize) -> Result<Self::SerializeTuple, ShapeError> {
        unsupported("a tuple")
    }
    fn serialize_tuple_struct(
        self,
        _: &'static str,
        _: usize,
    ) -> Result<Self::SerializeTupleStruct, ShapeError> {
        unsupported("a tuple struct")
    }
    fn serialize_tuple_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Self::SerializeTupleVariant, ShapeError> {
        unsupported("an enum")
    }
    fn serialize_map(self, _: Option<usize>) -> Result<Self::SerializeMap, ShapeError> {
        unsupported("a map")
    }
    fn serialize_struct(self, _: &'static str, _: usize) -> Result<StructRec, ShapeError> {
        Ok(StructRec(Vec::new()))
    }
    fn serialize_struct_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Self::SerializeStructVariant, ShapeError> {
        unsupported("an enum")
    }
}

impl ser::SerializeSeq for SeqRec {
    type Ok = Shape;
    type Error = ShapeError;
    fn serialize_element<T: ?Sized + Serialize>(&mut self, v: &T) -> Result<(), ShapeError> {
        self.0.push(v.serialize(Recorder)?);
        Ok(())
    }
    fn end(self) -> Result<Shape, ShapeError> {
        Ok(Shape::Seq(self.0.into_iter().next().map(Box::new)))
    }
}

impl ser::SerializeStruct for StructRec {
    type Ok = Shape;
    type Error = ShapeError;
    fn serialize_field<T: ?Sized + Serialize>(
        &mut self,
        key: &'static str,
        v: &T,
    ) -> Result<(), ShapeError> {
        self.0.push((key.to_string(), v.serialize(Recorder)?));
        Ok(())
    }
    fn end(self) -> Result<Shape, ShapeError> {
        Ok(Shape::Struct(self.0))
    }
}

/// Parses the fields of a `.msg` file into shapes (constants and comments skipped).
/// `nested` resolves a non-primitive type name (e.g. `builtin_interfaces/Time`).
pub fn parse_msg(
    text: &str,
    nested: &dyn Fn(&str) -> Option<Shape>,
) -> Result<Vec<(String, Shape)>, String> {
    let mut fields = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let mut parts = line.split_whitespace();
        let (Some(ty), Some(name)) = (parts.next(), parts.next()) else {
            return Err(format!("line {}: expected `type name`: {raw}", i + 1));
        };
        if name.contains('=') || parts.clone().next().is_some_and(|p| p.starts_with('=')) {
            continue; // a constant
        }
        let (base, seq) = match ty.find('[') {
            Some(k) if ty[k..] == *"[]" => (&ty[..k], true),
            Some(_) => {
                return Err(format!(
                    "line {}: bounded arrays are not used here: {raw}",
                    i + 1
                ))
            }
            None => (ty, false),
        };
        let elem = match base {
            "bool" => Shape::Bool,
            "byte" | "uint8" | "char" => Shape::U8,
            "int8" => Shape::I8,
            "int16" => Shape::I16,
            "uint16" => Shape::U16,
            "int32" => Shape::I32,
            "uint32" => Shape::U32,
            "int64" => Shape::I64,
            "uint64" => Shape::U64,
            "float32" => Shape::F32,
            "float64" => Shape::F64,
            "string" => Shape::Str,
            other => {
                nested(other).ok_or_else(|| format!("line {}: unknown type {other}", i + 1))?
            }
        };
        let shape = if seq {
            Shape::Seq(Some(Box::new(elem)))
        } else {
            elem
        };
        fields.push((name.to_string(), shape));
    }
    Ok(fields)
}
