"""Name and type of the Vulkan device Taichi will use, read from the Vulkan loader via ctypes.

Taichi does not report which physical device it runs on; this asks ``libvulkan`` directly
(vkCreateInstance, vkEnumeratePhysicalDevices, vkGetPhysicalDeviceProperties) and returns the
device Taichi prefers (a discrete GPU, then an integrated one, then any other).
"""

from __future__ import annotations

import ctypes
import ctypes.util

# VkPhysicalDeviceType
_TYPES = {0: "other", 1: "gpu", 2: "gpu", 3: "other", 4: "cpu"}
_RANK = {2: 0, 1: 1, 3: 2, 4: 3, 0: 4}


class _InstanceCreateInfo(ctypes.Structure):
    _fields_ = [
        ("sType", ctypes.c_uint32),
        ("pNext", ctypes.c_void_p),
        ("flags", ctypes.c_uint32),
        ("pApplicationInfo", ctypes.c_void_p),
        ("enabledLayerCount", ctypes.c_uint32),
        ("ppEnabledLayerNames", ctypes.c_void_p),
        ("enabledExtensionCount", ctypes.c_uint32),
        ("ppEnabledExtensionNames", ctypes.c_void_p),
    ]


def _largest_device_heap(lib, handle) -> int:
    """Bytes of the device's largest device-local memory heap (vkGetPhysicalDeviceMemoryProperties:
    memoryTypeCount, 32 memory types of 8 bytes, memoryHeapCount at byte 260, then 16 heaps of 16
    bytes from byte 264: size (uint64), flags (uint32; bit 0 DEVICE_LOCAL)); 0 if none is reported."""
    mem = ctypes.create_string_buffer(1024)  # VkPhysicalDeviceMemoryProperties is 520 bytes
    lib.vkGetPhysicalDeviceMemoryProperties(ctypes.c_void_p(handle), mem)
    raw = mem.raw
    count = min(int.from_bytes(raw[260:264], "little"), 16)
    sizes = [int.from_bytes(raw[264 + 16 * i : 272 + 16 * i], "little") for i in range(count)
             if int.from_bytes(raw[272 + 16 * i : 276 + 16 * i], "little") & 1]  # fmt: skip
    return max(sizes, default=0)


def vulkan_devices() -> list[dict]:
    """[{"name", "kind" ("gpu"|"cpu"|"other"), "type", "api", "heap"}] for every Vulkan device ("heap":
    bytes of its largest device-local memory heap, 0 if unknown); [] if none."""
    path = ctypes.util.find_library("vulkan") or "libvulkan.so.1"
    try:
        lib = ctypes.CDLL(path)
    except OSError:
        return []
    info = _InstanceCreateInfo(sType=1)  # VK_STRUCTURE_TYPE_INSTANCE_CREATE_INFO
    instance = ctypes.c_void_p()
    if lib.vkCreateInstance(ctypes.byref(info), None, ctypes.byref(instance)) != 0:
        return []
    try:
        count = ctypes.c_uint32(0)
        lib.vkEnumeratePhysicalDevices(instance, ctypes.byref(count), None)
        handles = (ctypes.c_void_p * count.value)()
        lib.vkEnumeratePhysicalDevices(instance, ctypes.byref(count), handles)
        found = []
        for h in handles[: count.value]:
            props = ctypes.create_string_buffer(2048)  # VkPhysicalDeviceProperties is ~824 bytes
            lib.vkGetPhysicalDeviceProperties(ctypes.c_void_p(h), props)
            words = (ctypes.c_uint32 * 5).from_buffer(props)
            name = props.raw[20 : 20 + 256].split(b"\0", 1)[0].decode("utf-8", "replace")
            api = f"{words[0] >> 22}.{(words[0] >> 12) & 0x3FF}.{words[0] & 0xFFF}"
            found.append({"name": name, "type": int(words[4]), "kind": _TYPES.get(int(words[4]), "other"), "api": api,
                          "heap": _largest_device_heap(lib, h)})  # fmt: skip
        return sorted(found, key=lambda d: _RANK.get(d["type"], 9))
    finally:
        lib.vkDestroyInstance(instance, None)
