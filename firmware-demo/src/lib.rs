//! Control-loop logic shared by the host demo and the freestanding build.
#![no_std]
