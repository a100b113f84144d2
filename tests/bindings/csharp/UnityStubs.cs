// Just enough of UnityEngine's surface to compile bindings/csharp/FlameExample.cs (and Flame.cs
// with UNITY_5_3_OR_NEWER defined) outside Unity and drive it from FlameExampleTest.cs.
using System;

namespace UnityEngine
{
    public class Object { }
    public class Component : Object { }
    public class Behaviour : Component { }
    public class MonoBehaviour : Behaviour { }
    public class TextAsset : Object { public byte[] bytes { get { return null; } } }
    public static class Application { public static string streamingAssetsPath { get { return ""; } } }
    public static class Time { public static float time; }   // set by the test
    public struct Quaternion
    {
        public float x, y, z, w;
        public Quaternion(float x, float y, float z, float w) { this.x = x; this.y = y; this.z = z; this.w = w; }
    }
    public struct Vector3
    {
        public float x, y, z;
        public Vector3(float x, float y, float z) { this.x = x; this.y = y; this.z = z; }
    }
    public class Transform : Component
    {
        public Quaternion localRotation;
        public Vector3 localPosition;
    }
    public static class Debug { public static void LogError(object message) { Console.Error.WriteLine("Debug.LogError: " + message); } }
    [AttributeUsage(AttributeTargets.Field)]
    public sealed class TooltipAttribute : Attribute { public TooltipAttribute(string tooltip) { } }
}

namespace AOT
{
    // In Unity this lives in UnityEngine.dll; Flame.cs defines it only outside Unity.
    [AttributeUsage(AttributeTargets.Method)]
    public sealed class MonoPInvokeCallbackAttribute : Attribute { public MonoPInvokeCallbackAttribute(Type type) { } }
}
